"""Albedo and normal maps of any photos, and diffuse relighting under an HDR environment (``ultrastage predict``).

For each photo (PNG or JPEG, any size, EXIF orientation applied) in a folder, each given checkpoint's network
predicts its map; outputs go to ``OUT/<photo stem>/``: ``albedo.exr`` (linear) and ``albedo.png`` (sRGB),
``normal.exr`` (camera frame, OpenCV axes, 0 off the mask) and ``normal.png`` ((n + 1) / 2). A photo with an
alpha channel is masked by it (alpha >= 0.5), as the networks were trained on masked subjects on black;
without one the whole frame is the subject.

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

__all__ = ["PHOTO_SUFFIXES", "ENVIRONMENT_SUFFIXES", "CAMERA_FROM_ENVIRONMENT", "PredictResult", "list_photos",
           "read_photo", "list_environments", "environment_sh_camera", "relight", "predict_folder"]

PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg")
ENVIRONMENT_SUFFIXES = (".hdr", ".pic", ".exr")
CAMERA_FROM_ENVIRONMENT = np.diag([1.0, -1.0, -1.0])
"""The assumed pose of a photo's camera in the environment's frame (module docstring): it looks along -z,
+y up."""
RELIT_PNG_PERCENTILE_VALUE = 0.8
"""The relit PNG's exposure puts the subject's 99th percentile here."""


@dataclass
class PredictResult:
    """What :func:`predict_folder` wrote."""

    photos: list[str] = field(default_factory=list)
    """Photo file names, in the order processed."""
    files: list[Path] = field(default_factory=list)
    """Every file written."""


def list_photos(folder: str | Path) -> list[Path]:
    """The PNG / JPEG files of a folder (not recursive), sorted by name.

    Raises:
        InputError: not a folder, no photos, or two photos with the same stem (their outputs would collide).
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "images folder not found")
    photos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in PHOTO_SUFFIXES)
    if not photos:
        raise InputError(folder, f"no images ({', '.join(PHOTO_SUFFIXES)}) in the folder")
    stems: dict[str, Path] = {}
    for p in photos:
        if p.stem in stems:
            raise InputError(p, f"same name as {stems[p.stem].name}: their outputs would share OUT/{p.stem}/")
        stems[p.stem] = p
    return photos


def read_photo(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """A photo as the networks take it: (H, W, 3) float32 sRGB in [0, 1], multiplied by the mask, and the
    mask (H, W) bool (alpha >= 0.5 when the file has alpha, else everywhere).

    Raises:
        InputError: unreadable or empty image.
    """
    from PIL import Image, ImageOps

    path = Path(path)
    try:
        with Image.open(path) as img:
            img = ImageOps.exif_transpose(img)
            has_alpha = img.mode in ("RGBA", "LA", "PA") or (img.mode == "P" and "transparency" in img.info)
            rgba = np.asarray(img.convert("RGBA" if has_alpha else "RGB"))
    except Exception as error:  # PIL raises several kinds for corrupt files
        raise InputError(path, f"cannot read image: {error}") from error
    if rgba.ndim != 3 or rgba.shape[0] < 1 or rgba.shape[1] < 1:
        raise InputError(path, f"empty image (shape {rgba.shape})")
    mask = rgba[..., 3] >= 128 if has_alpha else np.ones(rgba.shape[:2], bool)
    image = rgba[..., :3].astype(np.float32) / 255.0 * mask[..., None]
    return image, mask


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


def predict_folder(checkpoints: list[str | Path], images: str | Path, out: str | Path,
                   environment: str | Path | None = None, rotation_deg: float = 0.0, device: str = "auto",
                   log=print) -> PredictResult:
    """Maps (and relit images) of every photo of ``images`` into ``out`` (module docstring). Every input is
    read and checked before anything is written.

    Raises:
        InputError: a bad checkpoint, two of one network, no photos or an unreadable one, a missing, empty or
            corrupt environment. ConfigError: an environment without both networks' checkpoints.
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
    photos = list_photos(images)
    for photo in photos:  # every photo readable before the first output
        read_photo(photo)

    out = Path(out)
    result = PredictResult()
    for photo in photos:
        image, mask = read_photo(photo)
        folder = out / photo.stem
        maps = {name: predict_image(model, image, torch_device) for name, model in networks.items()}
        if "albedonet" in maps:
            albedo = maps["albedonet"] * mask[..., None]
            result.files += [write_exr(folder / "albedo.exr", albedo),
                             write_png(folder / "albedo.png", (srgb_encode(albedo) * 255 + 0.5).astype(np.uint8))]
        if "normalnet" in maps:
            normal = maps["normalnet"] * mask[..., None]
            result.files += [write_exr(folder / "normal.exr", normal, half=False),
                             write_png(folder / "normal.png", preview_normals(normal, mask.astype(np.float32)))]
        for env_name, sh_camera in environments.items():
            relit = relight(maps["albedonet"], maps["normalnet"], mask, sh_camera)
            rgba = np.concatenate([relit, mask[..., None].astype(np.float32)], axis=-1)
            result.files += [write_exr(folder / f"relit_{env_name}.exr", rgba, half=False),  # a sun exceeds half
                             write_png(folder / f"relit_{env_name}.png", _tone_map(relit, mask))]
        result.photos.append(photo.name)
        log(f"  {photo.name}: {', '.join(sorted(p.name for p in result.files if p.parent == folder))}")
    return result
