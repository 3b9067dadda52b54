"""One relighting set from the relighting sets of several releases, split by subject.

A release holds the relighting-set examples of its own actions (``manifests/relight_examples.parquet``,
``relight/<example_id>/``). A set to train and test on is drawn from many releases (subjects are captured in
sessions and batches), so :func:`merge_relight_sets` writes a folder in the release's layout that holds only a
relighting set: ``relight/<example_id>/`` (the sources' files, hard-linked where the file system allows, else
copied), ``relight/splits/<split>.txt``, ``manifests/relight_examples.parquet``, ``manifests/assets.parquet`` (so
``ultrastage verify`` checks it), the first source's ``CONVENTIONS.md`` and ``merge.json`` (the sources, the
subjects of each split and how they were chosen). ``ultrastage train --set`` and any Parquet reader load it as
they load a release.

Ids: an example ``A0000_00`` of the source named ``hair`` becomes ``hair_A0000_00`` (its action
``hair_A0000``), so ids stay unique; its ``example.json`` is its new row.

Subjects (``subject_from``):

- ``"subject"``: the sources' ``subject`` column as is: one subject seen in several releases (a person captured in
  two sessions) stays one subject, in one split;
- ``"release"``: each source's subjects are its own, named ``<source>/<subject>``: for sources whose subject
  names do not tell their subjects apart (the simulator names a subject by its skin, so bodies of one skin share
  a name).

Splits: the subjects named in ``test`` and ``validation`` (a subject's name, or a source's name for all of its
subjects) go there and every other subject to train; with neither given, each subject is drawn from ``seed`` and
``split_ratios`` as the relightset stage draws it (:func:`stages.numerics.relightset.split_of`). A subject's
examples are always in one split.

The folder is built under a temporary name beside ``out`` and renamed into place when complete; an existing
``out`` is refused unless ``replace`` is set (then it is swapped out only once the new set is whole).

    from ultrastage.merge_sets import merge_relight_sets, parse_sources
    merge_relight_sets(parse_sources(["panel/subjects/hair/release", "tall=panel/subjects/tall/release"]),
                       "panel_set", subject_from="release", test=("tall",))
"""
from __future__ import annotations

import json
import os
import re
import shutil
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Sequence

from pipeline.errors import ConfigError, InputError

__all__ = ["SetSource", "MergeResult", "parse_sources", "merge_relight_sets", "FILE_KINDS", "FILE_COLUMNS"]

FILE_KINDS = {"image_exr": "relight_image", "image_png": "relight_image_png", "albedo_exr": "relight_albedo",
              "albedo_png": "relight_albedo_png", "normal_exr": "relight_normal", "normal_png": "relight_normal_png",
              "mask_png": "relight_mask"}
"""The relight_examples columns that hold an example's files (paths relative to the release root) and the
assets table's kind of each."""
FILE_COLUMNS = tuple(FILE_KINDS)

MERGE_RECORD = "merge.json"
"""The merged set's record of its sources and splits, at its root."""

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


@dataclass(frozen=True)
class SetSource:
    """One release whose relighting set is merged."""

    name: str
    """Short name of the source: the prefix of its example and action ids (letters, digits, '.', '_', '-')."""
    release: Path
    """The release folder."""


@dataclass
class MergeResult:
    """What :func:`merge_relight_sets` wrote."""

    out: Path
    """The merged set's folder."""
    examples: dict[str, int] = field(default_factory=dict)
    """Examples per split."""
    subjects: dict[str, list[str]] = field(default_factory=dict)
    """Subjects per split."""


def parse_sources(specs: Sequence[str]) -> list[SetSource]:
    """Sources from ``NAME=PATH`` or ``PATH`` strings; a bare path is named after its folder, or after the folder
    above it when it is called ``release`` (``subjects/hair/release`` is ``hair``).

    Raises:
        ConfigError: a name that is not letters, digits, '.' and '-', or two sources of one name.
    """
    sources = []
    for text in specs:
        name, sep, path = text.partition("=")
        if not sep:
            path = text
            folder = Path(text).resolve()
            name = folder.parent.name if folder.name == "release" else folder.name
        if not _NAME.match(name):
            raise ConfigError(f"source {text!r}: name {name!r} must be letters, digits, '.', '_' and '-' "
                              "(it prefixes the example ids; give NAME=PATH)")
        sources.append(SetSource(name, Path(path)))
    names = [s.name for s in sources]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ConfigError(f"two sources named {', '.join(twice)}: give each a name as NAME=PATH")
    if not sources:
        raise ConfigError("no source release given")
    return sources


def _assign_splits(subjects_by_source: dict[str, list[str]], test: Sequence[str], validation: Sequence[str],
                   seed: int, split_ratios: Sequence[float]) -> dict[str, str]:
    """The split of every subject (see the module's docstring)."""
    from stages.numerics.relightset import split_of

    all_subjects = sorted({s for subjects in subjects_by_source.values() for s in subjects})
    if not test and not validation:
        return {s: split_of(seed, s, split_ratios) for s in all_subjects}
    chosen: dict[str, str] = {}
    for split, tokens in (("test", test), ("validation", validation)):
        for token in tokens:
            matched = [s for s in all_subjects if s == token] or list(subjects_by_source.get(token, ()))
            if not matched:
                raise ConfigError(f"--{split} {token!r}: no such subject or source (subjects: "
                                  f"{', '.join(all_subjects)}; sources: {', '.join(subjects_by_source)})")
            for subject in matched:
                if chosen.get(subject, split) != split:
                    raise ConfigError(f"subject {subject!r} is named for both {chosen[subject]} and {split}")
                chosen[subject] = split
    return {s: chosen.get(s, "train") for s in all_subjects}


def merge_relight_sets(sources: Sequence[SetSource], out: str | Path,
                       subject_from: Literal["subject", "release"] = "subject", test: Sequence[str] = (),
                       validation: Sequence[str] = (), seed: int = 0,
                       split_ratios: Sequence[float] = (0.8, 0.1, 0.1), replace: bool = False,
                       log=print) -> MergeResult:
    """Write the relighting sets of ``sources`` as one set in ``out`` (see the module's docstring).

    Every source is read and checked before anything is written: each must be a release with a non-empty
    relighting set whose files exist and match the sha256 its assets table gives them.

    Raises:
        InputError: a source that is not a release, has no relighting set, or misses or changed a file (naming
            the file). ConfigError: an unknown ``subject_from``, an unknown subject in ``test``/``validation``,
            a subject in both, no example left for train, or ``out`` exists and ``replace`` is not set.
    """
    from manifests.catalog import write_split_lists
    from manifests.writer import asset_row, file_sha256, write_table
    from pipeline.store import link_or_copy, swap_into_place
    from ultrastage.baselines.data import open_relight_set

    if subject_from not in ("subject", "release"):
        raise ConfigError(f"subject_from {subject_from!r}: must be 'subject' or 'release'")
    out = Path(out)
    if out.exists() and not replace:
        raise ConfigError(f"{out}: exists; choose another folder or replace it (--replace)")

    records: dict[str, list[dict[str, Any]]] = {}  # the rows of each source's relight_examples, as Python values
    roots: dict[str, Path] = {}
    shas: dict[str, dict[str, str]] = {}
    conventions: dict[str, Path] = {}
    for source in sources:
        release = open_relight_set(source.release)
        rows_of_source = release.table("relight_examples").to_pylist()
        assets = release.table("assets") if release.has_table("assets") else None
        known = dict(zip(assets.column("path").to_pylist(), assets.column("sha256").to_pylist())) \
            if assets is not None else {}
        for record in rows_of_source:
            for column in FILE_COLUMNS:
                rel = record[column]
                path = release.root / rel
                if not path.is_file():
                    raise InputError(path, f"file of the relighting set of source {source.name!r} not found")
                if rel in known:
                    shas.setdefault(source.name, {})[rel] = known[rel]
        records[source.name], roots[source.name] = rows_of_source, release.root
        if (release.root / "CONVENTIONS.md").is_file():
            conventions[source.name] = release.root / "CONVENTIONS.md"

    def subject_of(source: str, subject: str) -> str:
        return subject if subject_from == "subject" else f"{source}/{subject}"

    subjects_by_source = {name: sorted({subject_of(name, r["subject"]) for r in examples})
                          for name, examples in records.items()}
    split_of_subject = _assign_splits(subjects_by_source, test, validation, seed, split_ratios)
    if "train" not in split_of_subject.values():
        raise ConfigError("no subject is left for the train split")

    tmp = out.parent / f".{out.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp"
    tmp.mkdir(parents=True)
    try:
        rows: list[dict[str, Any]] = []
        asset_rows: list[dict[str, Any]] = []
        for source in sources:
            root = roots[source.name]
            for record in records[source.name]:
                example_id = f"{source.name}_{record['example_id']}"
                action_id = f"{source.name}_{record['action_id']}"
                subject = subject_of(source.name, record["subject"])
                row = dict(record, example_id=example_id, action_id=action_id, subject=subject,
                           split=split_of_subject[subject])
                folder = tmp / "relight" / example_id
                folder.mkdir(parents=True)
                for column in FILE_COLUMNS:
                    src = root / record[column]
                    dst = folder / Path(record[column]).name
                    link_or_copy(src, dst)
                    digest = {"bytes": dst.stat().st_size, "sha256": file_sha256(dst)}
                    expected = shas.get(source.name, {}).get(record[column])
                    if expected is not None and expected != digest["sha256"]:
                        raise InputError(src, f"differs from the sha256 its release's assets table gives it "
                                              f"(source {source.name!r}; `ultrastage verify {root}` lists it)")
                    row[column] = dst.relative_to(tmp).as_posix()
                    asset_rows.append(asset_row(tmp, dst, FILE_KINDS[column], action_id=action_id, digest=digest))
                example_json = folder / "example.json"
                example_json.write_text(json.dumps(row, indent=1, sort_keys=True))
                asset_rows.append(asset_row(tmp, example_json, "relight_example", action_id=action_id))
                rows.append(row)
        write_table(tmp, "relight_examples", rows)
        asset_rows += write_split_lists(tmp)
        if conventions:
            first = next(iter(conventions))
            shutil.copy2(conventions[first], tmp / "CONVENTIONS.md")
            asset_rows.append(asset_row(tmp, tmp / "CONVENTIONS.md", "document"))
            differing = [n for n, p in conventions.items() if p.read_bytes() != conventions[first].read_bytes()]
            if differing:
                log(f"note: CONVENTIONS.md of {', '.join(differing)} differs from {first}'s (kept {first}'s); "
                    "the sources were written by different pipeline versions")
        result = MergeResult(out)
        for split in ("train", "validation", "test"):
            result.examples[split] = sum(r["split"] == split for r in rows)
            result.subjects[split] = sorted(s for s, sp in split_of_subject.items() if sp == split)
        record = {
            "sources": [{"name": s.name, "release": str(s.release), "examples": len(records[s.name]),
                         "subjects": subjects_by_source[s.name]} for s in sources],
            "subject_from": subject_from,
            "splits_from": "named" if (test or validation) else "drawn",
            "test": list(test), "validation": list(validation),
            "seed": int(seed), "split_ratios": [float(r) for r in split_ratios],
            "examples": result.examples, "subjects": result.subjects,
        }
        (tmp / MERGE_RECORD).write_text(json.dumps(record, indent=1) + "\n")
        asset_rows.append(asset_row(tmp, tmp / MERGE_RECORD, "document"))
        write_table(tmp, "assets", asset_rows)
        swap_into_place(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    for split in ("train", "validation", "test"):
        log(f"{split:<10} {result.examples[split]:>5} examples, {len(result.subjects[split])} subject(s)"
            + (f": {', '.join(result.subjects[split])}" if result.subjects[split] else ""))
    if not result.examples["test"]:
        log("note: the test split is empty (`ultrastage train` measures the test split; name subjects with --test)")
    return result

