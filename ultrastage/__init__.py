"""The top of the project: the ``ultrastage`` command line (:mod:`ultrastage.cli`), the run wiring that joins the
engine to the release's Parquet manifests (:mod:`ultrastage.run`) and the single-image baselines trained on a
release's relighting set (:mod:`ultrastage.baselines`). It is the one package that may import every other one;
no other package imports it."""
