"""The artifact facade, the one door through which the stages and the consumer API read the stages' products.

- :mod:`artifacts.layout`: where each product lies (``PRODUCTS``: its stage and path in that stage's artifact
  folder; ``RELEASE_KINDS``: its kind in a release's assets manifest) and :class:`artifacts.layout.ArtifactWriter`,
  the paths a stage writes its products at.
- :mod:`artifacts.facade`: :class:`artifacts.facade.ActionArtifacts`, the products of one action read by what they
  are, over the work store or one action of a release.
- :mod:`artifacts.camera` and :mod:`artifacts.atlas`: the types the readers return (:class:`Camera`,
  :class:`Atlas`), which the numerics compute with.

It sits below both ``stages`` and ``manifests``: it imports the engine (``pipeline``) and ``calibration`` only.
"""
