"""`make compat`: load a release with other tools' own loaders, in their own environment (.venv-compat).

Not part of the test suite (nerfstudio is heavy): run by ``make compat RUN=runs/default``. Checks, per
published action:

- nerfstudio's ``NerfstudioDataParser`` parses ``transforms.json`` (cameras, images, masks, seed points);
- nerfstudio's ``ColmapDataParser`` parses ``colmap/sparse/0`` with the action folder as the image folder;
- COLMAP's own Python reader (``read_write_model``, as shipped in nerfstudio; gaussian-splatting's
  ``scene/colmap_loader.py`` is a copy of the same functions) reads the text model, and every image name
  is a file under the action folder, as gaussian-splatting's ``readColmapSceneInfo`` joins them.

Prints one line per check and exits 1 when one fails.
"""
from __future__ import annotations

import sys
from pathlib import Path


def check_action(folder: Path) -> list[str]:
    from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParserConfig
    from nerfstudio.data.dataparsers.nerfstudio_dataparser import NerfstudioDataParserConfig
    from nerfstudio.data.utils.colmap_parsing_utils import read_cameras_text, read_images_text, read_points3D_text

    failures = []
    try:
        outputs = NerfstudioDataParserConfig(data=folder, downscale_factor=1, load_3D_points=True).setup().get_dataparser_outputs("train")
        n = len(outputs.image_filenames)
        points = outputs.metadata.get("points3D_xyz")
        if outputs.mask_filenames is None or points is None:
            raise ValueError(f"no masks ({outputs.mask_filenames is None}) or no seed points ({points is None})")
        print(f"  nerfstudio NerfstudioDataParser: {n} train images with masks, {len(points)} seed points")
    except Exception as exc:  # noqa: BLE001 - report every loader's failure, then exit 1
        failures.append(f"{folder}: NerfstudioDataParser: {type(exc).__name__}: {exc}")
    try:
        outputs = ColmapDataParserConfig(data=folder, colmap_path=Path("colmap/sparse/0"), images_path=Path("."),
                                         downscale_factor=1, load_3D_points=True).setup().get_dataparser_outputs("train")
        print(f"  nerfstudio ColmapDataParser: {len(outputs.image_filenames)} train images")
    except Exception as exc:  # noqa: BLE001
        failures.append(f"{folder}: ColmapDataParser: {type(exc).__name__}: {exc}")
    model = folder / "colmap" / "sparse" / "0"
    try:
        cameras = read_cameras_text(model / "cameras.txt")
        images = read_images_text(model / "images.txt")
        points = read_points3D_text(model / "points3D.txt")
        missing = [im.name for im in images.values() if not (folder / im.name).is_file()]
        if missing:
            raise FileNotFoundError(f"image names that are no file under {folder}: {missing[:3]}")
        print(f"  COLMAP read_write_model: {len(cameras)} cameras, {len(images)} images, {len(points)} points")
    except Exception as exc:  # noqa: BLE001
        failures.append(f"{folder}: COLMAP text reader: {type(exc).__name__}: {exc}")
    return failures


def main(release: str) -> int:
    actions = sorted(p for p in (Path(release) / "actions").iterdir() if p.is_dir() and not p.name.startswith("."))
    if not actions:
        print(f"{release}: no published action to check", file=sys.stderr)
        return 1
    failures = []
    for folder in actions:
        print(folder)
        failures += check_action(folder)
    for line in failures:
        print(f"FAILED {line}", file=sys.stderr)
    print("OK" if not failures else f"{len(failures)} check(s) failed")
    return 1 if failures else 0


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: check_release.py RELEASE")
    sys.exit(main(sys.argv[1]))
