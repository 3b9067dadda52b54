"""Albedo and normal maps of any photos, and diffuse relighting under an HDR environment (``ultrastage predict``).

For each photo (PNG or JPEG, any size, EXIF orientation applied) in a folder, each given checkpoint's network
predicts its map; outputs go to ``OUT/<photo stem>/``: ``albedo.exr`` (linear) and ``albedo.png`` (sRGB),
``normal.exr`` (camera frame, OpenCV axes, 0 off the mask) and ``normal.png`` ((n + 1) / 2).

**Masks.** The networks were trained on masked subjects on black, so each photo ``NAME.*`` is multiplied by its
mask: its mask file, beside it as ``NAME_mask.<png|jpg|jpeg>`` (the layout of PIFu's and Relighting Humans'
samples) or in ``--masks DIR`` as ``NAME.<...>`` or ``NAME_mask.<...>``; without one the photo's alpha channel (>=
0.5); without that the whole frame is the subject. The log says which mask each photo took, with a note for the
photos without a mask file. A mask file is white (>= 128 in its first channel, times its alpha when it has one; a
label image of 0 and 1 only: 1) on the subject, at the photo's size after EXIF orientation. A ``NAME_mask.*`` file
is never a photo itself, also when no ``NAME`` photo lies beside it (a note names it). Two mask files for one
photo, a mask of another size, or an empty one are refused, naming the file.

**Contact sheet.** ``OUT/contact_sheet.png``: a row per photo, a column each for the masked photo, the albedo,
the normals and each relit image, every tile fitted into :data:`CONTACT_TILE` pixels and labelled (the photo's
tile with its name and where its mask came from).

**Relighting** (both networks' checkpoints and ``--environment``): ``relit_<env>.exr`` (linear RGBA,
premultiplied by the mask) and ``relit_<env>.png`` (sRGB, exposure putting the subject's 99th percentile at
0.8) with the diffuse shading ``albedo / pi * E(n)``, ``E`` the order-2 SH irradiance
(:mod:`stages.numerics.sh`) of the environment in the photo's camera frame. A photo has no pose, so the
camera is ASSUMED upright at the centre of the environment, looking along the map's -z (the panorama's
centre column, u = 0.5) with the map's +y up: ``cam_from_world = diag(1, -1, -1)`` (OpenCV camera axes:
x right, y down, z forward). ``--environment-rotation DEG`` turns the environment about +y first (world
direction = R_y(DEG) map direction, the ``relight_examples`` convention), so the SH in the camera frame are
``project_environment(env, diag(1, -1, -1) @ rotation_y(DEG))``. No shadows, no specular, no
interreflection: the paper's AlbedoNet / NormalNet relighting.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.errors import ConfigError, InputError
from stages.numerics import sh

from .models import UNet, predict_image
from .train import load_network, select_device

__all__ = ["PHOTO_SUFFIXES", "MASK_SUFFIX", "ENVIRONMENT_SUFFIXES", "CAMERA_FROM_ENVIRONMENT", "CONTACT_SHEET_NAME",
           "CONTACT_TILE", "Photo", "PredictResult", "list_photos", "read_mask", "read_photo", "list_environments",
           "environment_sh_camera", "relight", "contact_sheet", "predict_folder"]

PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg")
MASK_SUFFIX = "_mask"
"""``NAME_mask.<png|jpg|jpeg>`` is the mask of photo ``NAME.*`` (module docstring)."""
CONTACT_SHEET_NAME = "contact_sheet.png"
CONTACT_TILE = 256
"""Each tile of the contact sheet: the picture scaled to fit a square of this many pixels, centred on grey."""
CONTACT_BACKGROUND = 48
"""Grey of a tile around its picture (the pictures' own background, off the mask, is black)."""
ENVIRONMENT_SUFFIXES = (".hdr", ".pic", ".exr")
CAMERA_FROM_ENVIRONMENT = np.diag([1.0, -1.0, -1.0])
"""The assumed pose of a photo's camera in the environment's frame (module docstring): it looks along -z,
+y up."""
RELIT_PNG_PERCENTILE_VALUE = 0.8
"""The relit PNG's exposure puts the subject's 99th percentile here."""


@dataclass(frozen=True)
class Photo:
    """A photo to predict and its mask file (None: its alpha channel, else the whole frame)."""

    path: Path
    """The photo."""
    mask: Path | None = None
    """Its mask file (``--masks DIR`` or ``NAME_mask.*`` beside it)."""


@dataclass
class PredictResult:
    """What :func:`predict_folder` wrote."""

    photos: list[str] = field(default_factory=list)
    """Photo file names, in the order processed."""
    masks: dict[str, str] = field(default_factory=dict)
    """Photo file name -> where its mask came from: the mask file's path, "alpha" or "none" (the whole frame)."""
    notes: list[str] = field(default_factory=list)
    """What the log said about the inputs: photos without a mask file, mask files without a photo."""
    files: list[Path] = field(default_factory=list)
    """Every file written (the contact sheet last)."""


def _is_image(path: Path) -> bool:
    return path.is_file() and path.suffix.lower() in PHOTO_SUFFIXES


def _images_by_stem(folder: Path) -> dict[str, list[Path]]:
    """The PNG / JPEG files of a folder by stem, each list sorted by name."""
    out: dict[str, list[Path]] = {}
    for p in sorted(folder.iterdir()):
        if _is_image(p):
            out.setdefault(p.stem, []).append(p)
    return out


def _is_mask_name(stem: str) -> bool:
    return stem.endswith(MASK_SUFFIX) and stem != MASK_SUFFIX


def list_photos(folder: str | Path, masks: str | Path | None = None, log=print) -> tuple[list[Photo], list[str]]:
    """The photos of a folder (PNG / JPEG, not recursive, sorted by name) with their mask files, and the notes
    the log got about them (module docstring: a ``NAME_mask.*`` file is a mask, never a photo; ``masks`` is a
    folder of masks named ``NAME.*`` or ``NAME_mask.*`` by the photos' stems).

    Raises:
        InputError: not a folder, no photos, two photos with the same stem (their outputs would collide), a
            masks folder that is not one, or two mask files for one photo.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "images folder not found")
    if masks is not None and not Path(masks).is_dir():
        raise InputError(masks, "masks folder not found")
    beside = _images_by_stem(folder)
    apart = {} if masks is None or Path(masks).resolve() == folder.resolve() else _images_by_stem(Path(masks))
    photo_stems = [stem for stem in beside if not _is_mask_name(stem)]
    notes = [f"{p.name}: a mask ({MASK_SUFFIX} name) with no photo {stem[:-len(MASK_SUFFIX)]}.* beside it; "
             "not predicted" for stem, paths in beside.items()
             if _is_mask_name(stem) and stem[:-len(MASK_SUFFIX)] not in beside for p in paths]
    if not photo_stems:
        raise InputError(folder, f"no images ({', '.join(PHOTO_SUFFIXES)}) in the folder"
                                 + (f" (only masks, named *{MASK_SUFFIX})" if beside else ""))
    photos = []
    for stem in photo_stems:
        paths = beside[stem]
        if len(paths) > 1:
            raise InputError(paths[1], f"same name as {paths[0].name}: their outputs would share OUT/{stem}/")
        found = apart.get(stem, []) + apart.get(stem + MASK_SUFFIX, []) + beside.get(stem + MASK_SUFFIX, [])
        if len(found) > 1:
            raise InputError(found[1], f"a second mask of {paths[0].name} (with {found[0]}): keep one")
        photos.append(Photo(paths[0], found[0] if found else None))
    photos.sort(key=lambda photo: photo.path.name)
    used = {photo.mask for photo in photos}
    notes += [f"{p}: in --masks but no photo {stem.removesuffix(MASK_SUFFIX)}.* in {folder}; not used"
              for stem, paths in apart.items() for p in paths if p not in used]
    for note in notes:
        log(f"  note: {note}")
    return photos, notes


def _read_pixels(path: Path, what: str) -> tuple[np.ndarray, bool]:
    """An image file's pixels, upright by its EXIF orientation: (H, W, 4) uint8 RGBA when it has alpha, else
    (H, W, 3) RGB, and whether it has alpha. InputError naming the file ("cannot read <what>") when PIL cannot."""
    from PIL import Image, ImageOps

    try:
        with Image.open(path) as img:
            img = ImageOps.exif_transpose(img)
            has_alpha = img.mode in ("RGBA", "LA", "PA") or (img.mode == "P" and "transparency" in img.info)
            return np.asarray(img.convert("RGBA" if has_alpha else "RGB")), has_alpha
    except Exception as error:  # PIL raises several kinds for corrupt files
        raise InputError(path, f"cannot read {what}: {error}") from error


def read_mask(path: str | Path, shape: tuple[int, int]) -> np.ndarray:
    """A mask file as an (H, W) bool mask of a photo of ``shape`` (H, W): its first channel (times its alpha
    when it has one) >= 128, or == 1 in a label image (values 0 and 1 only), EXIF orientation applied.

    Raises:
        InputError: unreadable, of another size than the photo, or empty.
    """
    path = Path(path)
    pixels, has_alpha = _read_pixels(path, "mask")
    if pixels.shape[:2] != tuple(shape):
        raise InputError(path, f"mask is {pixels.shape[1]} x {pixels.shape[0]} px, its photo "
                               f"{shape[1]} x {shape[0]} px")
    value = pixels[..., 0].astype(np.uint16)
    if has_alpha:
        value = value * pixels[..., 3] // 255
    mask = value >= 128 if value.max() > 1 else value == 1  # a label image (0 and 1 only): 1 is the subject
    if not mask.any():
        raise InputError(path, "mask is empty (no pixel >= 128): nothing to predict")
    return mask


def read_photo(path: str | Path, mask_path: str | Path | None = None) -> tuple[np.ndarray, np.ndarray, str]:
    """A photo as the networks take it: (H, W, 3) float32 sRGB in [0, 1], multiplied by the mask; the mask
    (H, W) bool (the mask file's when given, else alpha >= 0.5 when the file has alpha, else everywhere); and
    where it came from (``mask_path``, "alpha" or "none").

    Raises:
        InputError: unreadable or empty image; a bad mask file (:func:`read_mask`).
    """
    path = Path(path)
    rgba, has_alpha = _read_pixels(path, "image")
    if rgba.ndim != 3 or rgba.shape[0] < 1 or rgba.shape[1] < 1:
        raise InputError(path, f"empty image (shape {rgba.shape})")
    if mask_path is not None:
        mask, source = read_mask(mask_path, rgba.shape[:2]), str(mask_path)
    elif has_alpha:
        mask, source = rgba[..., 3] >= 128, "alpha"
    else:
        mask, source = np.ones(rgba.shape[:2], bool), "none"
    image = rgba[..., :3].astype(np.float32) / 255.0 * mask[..., None]
    return image, mask, source


def list_environments(path: str | Path) -> list[Path]:
    """One environment map file, or the maps (.hdr, .pic, .exr) of a folder sorted by name.

    Raises:
        InputError: not found, or a folder with no maps.
    """
    path = Path(path)
    if path.is_dir():
        found = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in ENVIRONMENT_SUFFIXES)
        if not found:
            raise InputError(path, f"no environment maps ({', '.join(ENVIRONMENT_SUFFIXES)}) in the folder")
        return found
    if not path.is_file():
        raise InputError(path, "environment map not found")
    return [path]


def environment_sh_camera(env: np.ndarray, rotation_deg: float = 0.0) -> np.ndarray:
    """Order-2 SH (9, 3) of an equirect environment (H, W, 3) in the assumed camera frame of a photo
    (module docstring), the environment first turned by ``rotation_deg`` about +y."""
    return sh.project_environment(env, CAMERA_FROM_ENVIRONMENT @ sh.rotation_y(rotation_deg))


def relight(albedo: np.ndarray, normal: np.ndarray, mask: np.ndarray, sh_camera: np.ndarray) -> np.ndarray:
    """Diffuse radiance (H, W, 3) float32 ``albedo / pi * E(n)`` on the mask (0 off it): albedo (H, W, 3)
    linear, normal (H, W, 3) unit camera-frame, mask (H, W) bool, sh_camera (9, 3)."""
    albedo = np.asarray(albedo, dtype=np.float32)
    normal = np.asarray(normal, dtype=np.float32)
    mask = np.asarray(mask, dtype=bool)
    if albedo.shape != normal.shape or albedo.ndim != 3 or albedo.shape[2] != 3 or mask.shape != albedo.shape[:2]:
        raise ValueError(f"expected albedo, normal (H, W, 3) and mask (H, W), got {albedo.shape}, {normal.shape}, "
                         f"{mask.shape}")
    out = np.zeros_like(albedo)
    if mask.any():
        n = normal[mask].astype(np.float64)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        out[mask] = (albedo[mask] / math.pi * sh.sh_irradiance(n, sh_camera)).astype(np.float32)
    return out


def _tone_map(linear: np.ndarray, mask: np.ndarray) -> np.ndarray:
    from pipeline.codecs.image import srgb_encode

    p99 = float(np.percentile(linear[mask], 99)) if mask.any() else 0.0
    exposure = RELIT_PNG_PERCENTILE_VALUE / p99 if p99 > 0 else 1.0
    return (srgb_encode(linear * exposure) * 255.0 + 0.5).astype(np.uint8)


def _tile(picture: np.ndarray, label: str, size: int = CONTACT_TILE) -> np.ndarray:
    """A (size, size, 3) uint8 tile: ``picture`` (H, W, 3) uint8 scaled to fit (nearest neighbour when it grows,
    so pixels stay pixels), centred on grey, labelled."""
    from PIL import Image

    from pipeline.codecs.image import label_picture

    h, w = picture.shape[:2]
    scale = size / max(h, w)
    nh, nw = max(1, round(h * scale)), max(1, round(w * scale))
    resample = Image.NEAREST if scale >= 1 else Image.LANCZOS
    scaled = np.asarray(Image.fromarray(np.ascontiguousarray(picture[..., :3])).resize((nw, nh), resample))
    tile = np.full((size, size, 3), CONTACT_BACKGROUND, np.uint8)
    top, left = (size - nh) // 2, (size - nw) // 2
    tile[top:top + nh, left:left + nw] = scaled
    return label_picture(tile, label)


def contact_sheet(rows: list[list[tuple[np.ndarray, str]]], size: int = CONTACT_TILE) -> np.ndarray:
    """One (rows * size, columns * size, 3) uint8 picture of rows of labelled pictures ((H, W, 3) uint8, text),
    each picture fitted into a (size, size) tile (:func:`_tile`), the columns the longest row's; shorter rows
    end in grey."""
    if not rows or not all(rows):
        raise ValueError("contact_sheet takes one or more rows of one or more pictures")
    columns = max(len(row) for row in rows)
    sheet = np.full((len(rows) * size, columns * size, 3), CONTACT_BACKGROUND, np.uint8)
    for r, row in enumerate(rows):
        for c, (picture, label) in enumerate(row):
            sheet[r * size:(r + 1) * size, c * size:(c + 1) * size] = _tile(picture, label, size)
    return sheet


def _mask_note(photo: Photo, source: str, masks: str | Path | None) -> str:
    """What the log says of a photo's mask."""
    if source == "alpha":
        return f"{photo.path.name}: no mask file; its alpha channel is the mask"
    if source == "none":
        stem = photo.path.stem
        where = f"no {stem}{MASK_SUFFIX}.png/.jpg beside it" + (f", none in {masks}" if masks is not None else "")
        return f"{photo.path.name}: no mask ({where}, no alpha channel): the whole frame is the subject"
    return f"{photo.path.name}: mask {source}"


def _shrink(picture: np.ndarray, size: int = CONTACT_TILE) -> np.ndarray:
    """``picture`` (H, W, 3) uint8 scaled down to fit a (size, size) square (as it is when it already fits)."""
    from PIL import Image

    h, w = picture.shape[:2]
    if max(h, w) <= size:
        return picture
    scale = size / max(h, w)
    size_wh = (max(1, round(w * scale)), max(1, round(h * scale)))
    return np.asarray(Image.fromarray(np.ascontiguousarray(picture)).resize(size_wh, Image.LANCZOS))


def predict_folder(checkpoints: list[str | Path], images: str | Path, out: str | Path,
                   environment: str | Path | None = None, rotation_deg: float = 0.0, device: str = "auto",
                   masks: str | Path | None = None, log=print) -> PredictResult:
    """Maps (and relit images) of every photo of ``images`` into ``out``, each masked by its mask (``masks``: a
    folder of mask files), and the contact sheet ``out/contact_sheet.png`` (module docstring). Every input is
    read and checked before anything is written; the log says which mask each photo took.

    Raises:
        InputError: a bad checkpoint, two of one network, no photos or an unreadable one, a bad mask file, a
            missing, empty or corrupt environment. ConfigError: an environment without both networks'
            checkpoints.
    """
    from pipeline.codecs.exr import write_exr
    from pipeline.codecs.hdr import read_environment
    from pipeline.codecs.image import preview_normals, srgb_encode, write_png

    if not math.isfinite(rotation_deg):
        raise ConfigError(f"--environment-rotation {rotation_deg}: must be a finite angle in degrees")
    torch_device = select_device(device)
    networks: dict[str, UNet] = {}
    for path in checkpoints:
        model, ckpt = load_network(path, device=torch_device)
        if ckpt["network"] in networks:
            raise InputError(path, f"a second {ckpt['network']} checkpoint (give at most one per network)")
        networks[ckpt["network"]] = model
    if not networks:
        raise ConfigError("no --checkpoint given")
    environments: dict[str, np.ndarray] = {}
    if environment is not None:
        if set(networks) != {"albedonet", "normalnet"}:
            raise ConfigError(f"--environment {environment}: relighting needs an albedonet and a normalnet "
                              f"checkpoint, got {sorted(networks)}")
        for env_path in list_environments(environment):
            if env_path.stem in environments:
                raise InputError(env_path, "two environment maps share this name")
            environments[env_path.stem] = environment_sh_camera(read_environment(env_path), rotation_deg)
    result = PredictResult()
    photos, result.notes = list_photos(images, masks, log)
    for photo in photos:  # every photo and mask readable before the first output
        if photo.path.stem == CONTACT_SHEET_NAME:
            raise InputError(photo.path, f"its outputs OUT/{photo.path.stem}/ would be the contact sheet's name")
        _, _, source = read_photo(photo.path, photo.mask)
        result.masks[photo.path.name] = source
        note = _mask_note(photo, source, masks)
        if source in ("alpha", "none"):
            result.notes.append(note)
        log(f"  {'note: ' if source in ('alpha', 'none') else ''}{note}")

    out = Path(out)
    rows = []
    for photo in photos:
        image, mask, source = read_photo(photo.path, photo.mask)
        folder = out / photo.path.stem
        maps = {name: predict_image(model, image, torch_device) for name, model in networks.items()}
        shown = Path(source).name if photo.mask is not None else {"alpha": "alpha", "none": "none, whole frame"}[source]
        row = [(_shrink((image * 255.0 + 0.5).astype(np.uint8)), f"{photo.path.name} (mask: {shown})")]
        if "albedonet" in maps:
            albedo = maps["albedonet"] * mask[..., None]
            albedo_png = (srgb_encode(albedo) * 255 + 0.5).astype(np.uint8)
            result.files += [write_exr(folder / "albedo.exr", albedo), write_png(folder / "albedo.png", albedo_png)]
            row.append((_shrink(albedo_png), "albedo"))
        if "normalnet" in maps:
            normal = maps["normalnet"] * mask[..., None]
            normal_png = preview_normals(normal, mask.astype(np.float32))
            result.files += [write_exr(folder / "normal.exr", normal, half=False),
                             write_png(folder / "normal.png", normal_png)]
            row.append((_shrink(normal_png), "normals"))
        for env_name, sh_camera in environments.items():
            relit = relight(maps["albedonet"], maps["normalnet"], mask, sh_camera)
            rgba = np.concatenate([relit, mask[..., None].astype(np.float32)], axis=-1)
            relit_png = _tone_map(relit, mask)
            result.files += [write_exr(folder / f"relit_{env_name}.exr", rgba, half=False),  # a sun exceeds half
                             write_png(folder / f"relit_{env_name}.png", relit_png)]
            row.append((_shrink(relit_png), f"relit {env_name}"))
        rows.append(row)
        result.photos.append(photo.path.name)
        log(f"  {photo.path.name}: {', '.join(sorted(p.name for p in result.files if p.parent == folder))}")
    result.files.append(write_png(out / CONTACT_SHEET_NAME, contact_sheet(rows)))
    log(f"  contact sheet: {out / CONTACT_SHEET_NAME} ({len(rows)} row(s): photo, "
        + ", ".join(label for _, label in rows[0][1:]) + ")")
    return result
