"""Raw decode: time per megapixel against error, for every demosaic algorithm and half-size decoding.

A known linear sRGB image (smooth gradients, flat colour patches, correlated skin-like texture, gratings of
rising frequency, a zone plate, hard edges) is
mosaicked through the inverse of LibRaw's colour pipeline into an uncompressed 14-bit RGGB DNG (no noise),
decoded with :func:`pipeline.codecs.raw.decode_raw`, and compared with the truth: PSNR (peak 1.0) over the
frame minus an 8-pixel border and per region (flat patches and smooth gradients check the colour pipeline;
texture, gratings and the zone plate rank the demosaic algorithms); half-size decodes against the 2x2 block
average of the truth. Time is the best of a few decodes of the file (file read and checks included), in ms per
megapixel of the raw frame, and as a ratio to two baselines timed in the same process: rawpy's default call on the
same file (``x_rawpy_default``) and a memory copy of the bytes a decode reads and writes (``x_memcpy``).
When ../shared/data holds the real Blackmagic DNG (lossless-JPEG compressed), its decode time is reported
too (no ground truth there).

    python bench/bench_decode.py --out bench/out [--quick]

``--quick`` (the tests' mode): a 384 x 256 frame, one decode per algorithm; the numbers are not measurements.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from _quick import QUICK_HELP  # noqa: E402
from pipeline.codecs.raw import decode_raw, supported_demosaic  # noqa: E402
from stages.numerics.metrics import downsample_to, psnr, ssim  # noqa: E402

SHARED_RAW = ROOT.parent / "shared" / "data" / "raw" / "Blackmagic_PocketCinema4K.dng"

XYZ_FROM_SRGB = np.array(
    [[0.4124564, 0.3575761, 0.1804375], [0.2126729, 0.7151522, 0.0721750], [0.0193339, 0.1191920, 0.9503041]]
)
CAM_FROM_XYZ = np.round(
    np.array([[0.7171, -0.1986, -0.0648], [-0.4885, 1.2465, 0.2631], [-0.0999, 0.1755, 0.7023]]) * 1e4
) / 1e4
NEUTRAL = (0.5, 1.0, 0.6)
BLACK, WHITE = 600, 16383
BORDER = 8


def _srat(m):
    return [x for v in np.ravel(m) for x in (int(round(v * 10000)), 10000)]


def write_dng(path: Path, raw: np.ndarray) -> None:
    import tifffile

    extratags = [
        (33421, "H", 2, (2, 2), True), (33422, "B", 4, (0, 1, 1, 2), True), (50706, "B", 4, (1, 4, 0, 0), True),
        (50707, "B", 4, (1, 1, 0, 0), True), (50708, "s", 0, "UltraStage Simulated D750", True),
        (50714, "I", 1, BLACK, True), (50717, "I", 1, WHITE, True), (50721, "2i", 9, _srat(CAM_FROM_XYZ), True),
        (50728, "2I", 3, [x for v in NEUTRAL for x in (int(round(v * 10000)), 10000)], True),
        (50778, "H", 1, 21, True), (271, "s", 0, "UltraStage", True), (272, "s", 0, "SimD750", True),
    ]
    tifffile.imwrite(path, raw, photometric=32803, extratags=extratags, subfiletype=0, compression=None,
                     metadata=None)


def mosaic(rgb: np.ndarray) -> np.ndarray:
    """Linear sRGB (H, W, 3) -> RGGB raw DN that LibRaw decodes back to it (white balance, colour matrix)."""
    cam_rgb = CAM_FROM_XYZ @ XYZ_FROM_SRGB
    cam_rgb = cam_rgb / cam_rgb.sum(axis=1, keepdims=True)
    neutral = np.asarray(NEUTRAL)
    cam = rgb.astype(np.float64) @ cam_rgb.T * (neutral / neutral.max())
    if cam.min() < 0:
        raise ValueError("truth image is outside the camera gamut")
    h, w = rgb.shape[:2]
    site = np.empty((h, w))
    site[0::2, 0::2] = cam[0::2, 0::2, 0]
    site[0::2, 1::2] = cam[0::2, 1::2, 1]
    site[1::2, 0::2] = cam[1::2, 0::2, 1]
    site[1::2, 1::2] = cam[1::2, 1::2, 2]
    return np.clip(np.round(site * (WHITE - BLACK) + BLACK), 0, 65535).astype(np.uint16)


def truth_image(h: int, w: int) -> np.ndarray:
    """Smooth + textured linear sRGB test image in [0.03, 0.75]."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    u, v = xx / w, yy / h
    img = np.empty((h, w, 3))
    # smooth colour gradients (a lit body)
    img[..., 0] = 0.15 + 0.35 * u
    img[..., 1] = 0.12 + 0.3 * v
    img[..., 2] = 0.1 + 0.25 * (1 - u) * v
    # colour patches with hard edges (upper-left quarter)
    patches = np.array([[0.5, 0.3, 0.2], [0.2, 0.4, 0.15], [0.15, 0.2, 0.5], [0.6, 0.55, 0.5], [0.08, 0.08, 0.08],
                        [0.45, 0.2, 0.35]])
    ph, pw = h // 8, w // 16
    for i, c in enumerate(patches):
        r0, c0 = ph * (1 + (i // 3)), pw * (1 + 2 * (i % 3))
        img[r0 : r0 + ph - 4, c0 : c0 + pw * 2 - 4] = c
    # gratings of rising frequency (skin pores .. hair), right half, luminance + chroma
    band = (u > 0.5) & (v < 0.5)
    f = 2.0 + 60.0 * ((u - 0.5) / 0.5) ** 2  # cycles per 100 px
    g = 0.5 + 0.45 * np.sin(2 * np.pi * f * xx / 100.0)
    img[band] = (0.1 + 0.5 * g[band])[:, None] * np.array([0.9, 0.75, 0.6])
    # radial zone plate (lower right): all orientations
    zone = (u > 0.55) & (v > 0.55)
    r2 = ((xx - 0.775 * w) ** 2 + (yy - 0.775 * h) ** 2) / (0.3 * min(h, w)) ** 2
    z = 0.5 + 0.45 * np.cos(np.pi * 40 * r2)
    img[zone] = (0.08 + 0.5 * z[zone])[:, None] * np.array([0.7, 0.8, 0.9])
    # fine texture in the lower-left quarter (skin): correlated noise, deterministic
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(7)
    tex = gaussian_filter(rng.standard_normal((h, w)), 1.5)
    tex /= tex.std()
    skin = (u < 0.5) & (v > 0.5)
    img[skin] *= 1.0 + 0.08 * tex[skin, None]
    return np.clip(img, 0.03, 0.75).astype(np.float32)


def regions(h: int, w: int) -> dict[str, np.ndarray]:
    """Named (H, W) bool regions of :func:`truth_image`, minus the border."""
    yy, xx = np.mgrid[0:h, 0:w]
    u, v = xx / w, yy / h
    inner = (yy >= BORDER) & (yy < h - BORDER) & (xx >= BORDER) & (xx < w - BORDER)
    ph, pw = h // 8, w // 16
    patches = np.zeros((h, w), bool)
    for i in range(6):
        r0, c0 = ph * (1 + (i // 3)), pw * (1 + 2 * (i % 3))
        patches[r0 + 6 : r0 + ph - 10, c0 + 6 : c0 + pw * 2 - 10] = True  # patch interiors, away from edges
    return {
        "all": inner,
        "flat_patches": inner & patches,
        "smooth": inner & (u > 0.05) & (u < 0.45) & (v > 0.42) & (v < 0.5),
        "skin_texture": inner & (u < 0.5) & (v > 0.5),
        "gratings": inner & (u > 0.5) & (v < 0.5),
        "zone_plate": inner & (u > 0.55) & (v > 0.55),
    }


def _time(fn, repeats: int) -> tuple[float, object]:
    best, out = float("inf"), None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def baselines(path: Path, h: int, w: int, repeats: int) -> tuple[float, float]:
    """Seconds (best of ``repeats``) of two simple baselines on the same file, in this process: rawpy's default call
    (``imread(...).postprocess()``: AHD to 8-bit sRGB with LibRaw's own defaults) and a memory copy of the bytes a
    decode reads and writes (the 16-bit raw frame in, an (h, w, 3) float32 image out)."""
    import rawpy

    def default_call():
        with rawpy.imread(str(path)) as raw:
            return raw.postprocess()

    default_s, _ = _time(default_call, repeats)
    src = np.ones(h * w * (2 + 12) // 4, np.float32)
    dst = np.empty_like(src)
    copy_s, _ = _time(lambda: np.copyto(dst, src), max(repeats, 5))
    return default_s, copy_s


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", default=str(ROOT / "bench" / "out"))
    parser.add_argument("--height", type=int, default=1024)
    parser.add_argument("--width", type=int, default=1536)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help=QUICK_HELP)
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    h, w = (256, 384) if args.quick else (args.height, args.width)
    repeats = 1 if args.quick else args.repeats
    truth = truth_image(h, w)
    mp = h * w / 1e6
    inner = (slice(BORDER, h - BORDER), slice(BORDER, w - BORDER))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "truth.dng"
        write_dng(path, mosaic(truth))
        decode_raw(path, demosaic="LINEAR")  # warm up (imports, page cache)
        regs = regions(h, w)
        baseline_s, memcpy_s = baselines(path, h, w, repeats)
        for alg in supported_demosaic():
            sec, frame = _time(lambda a=alg: decode_raw(path, demosaic=a), repeats)
            rows.append({"algorithm": alg, "half_size": False, "ms_per_mp": 1e3 * sec / mp,
                         "psnr_db": psnr(frame.rgb[inner], truth[inner]),
                         "ssim": ssim(frame.rgb[inner], truth[inner]),
                         "psnr_db_by_region": {k: psnr(frame.rgb, truth, m) for k, m in regs.items()}})
        sec, frame = _time(lambda: decode_raw(path, half_size=True), repeats)
        hs = frame.rgb.shape[:2]
        half_truth = downsample_to(truth, hs)
        hi = (slice(BORDER // 2, -BORDER // 2), slice(BORDER // 2, -BORDER // 2))
        rows.append({"algorithm": "HALF (any)", "half_size": True, "ms_per_mp": 1e3 * sec / mp,
                     "psnr_db": psnr(frame.rgb[hi], half_truth[hi]), "ssim": ssim(frame.rgb[hi], half_truth[hi]),
                     "psnr_db_by_region": {k: psnr(frame.rgb, half_truth, downsample_to(m, hs, kind="mask"))
                                           for k, m in regs.items()}})
        for r in rows:
            r["baseline_ms_per_mp"] = 1e3 * baseline_s / mp
            r["x_rawpy_default"] = r["ms_per_mp"] / r["baseline_ms_per_mp"]
            r["x_memcpy"] = r["ms_per_mp"] / (1e3 * memcpy_s / mp)

    real = []
    if SHARED_RAW.exists():
        for alg in ("LINEAR", "AHD", "DCB"):
            if alg not in supported_demosaic():
                continue
            sec, frame = _time(lambda a=alg: decode_raw(SHARED_RAW, demosaic=a), min(repeats, 2))
            real.append({"algorithm": alg, "half_size": False, "ms_per_mp": 1e3 * sec / (frame.raw_size[0] *
                         frame.raw_size[1] / 1e6)})
        sec, frame = _time(lambda: decode_raw(SHARED_RAW, half_size=True), min(repeats, 2))
        real.append({"algorithm": "HALF (any)", "half_size": True,
                     "ms_per_mp": 1e3 * sec / (frame.raw_size[0] * frame.raw_size[1] / 1e6)})

    print(f"synthetic {w}x{h} 14-bit RGGB DNG (no noise), PSNR over the frame minus {BORDER} px:")
    names = list(rows[0]["psnr_db_by_region"])[1:]
    print(f"{'algorithm':12s} {'half':>5s} {'ms/MP':>8s} {'PSNR dB':>8s} {'SSIM':>6s}  " +
          " ".join(f"{n[:12]:>12s}" for n in names))
    for r in rows:
        print(f"{r['algorithm']:12s} {str(r['half_size']):>5s} {r['ms_per_mp']:8.1f} {r['psnr_db']:8.2f} "
              f"{r['ssim']:6.4f}  " + " ".join(f"{r['psnr_db_by_region'][n]:12.2f}" for n in names))
    if real:
        print(f"real {SHARED_RAW.name} (4128x2176, compressed): " +
              ", ".join(f"{r['algorithm']} {r['ms_per_mp']:.0f} ms/MP" for r in real))

    result = {
        "bench": "decode",
        "what": "decode_raw time per megapixel of the raw frame vs PSNR against a known linear sRGB truth",
        "frame": {"width": w, "height": h, "bits": 14, "black": BLACK, "white": WHITE, "noise": "none"},
        "repeats": repeats,
        "quick": args.quick,
        "baselines": {"rawpy_default_ms_per_mp": 1e3 * baseline_s / mp, "memcpy_ms_per_mp": 1e3 * memcpy_s / mp,
                      "what": "rawpy.imread(...).postprocess() with LibRaw's defaults (AHD, 8-bit sRGB), and "
                              "np.copyto of the bytes a decode reads and writes (16-bit raw in, float32 RGB out), "
                              "timed in the same process; x_rawpy_default and x_memcpy per row"},
        "rows": rows,
        "real_dng": real,
        "notes": "half-size decodes do not demosaic (LibRaw ignores the algorithm); their PSNR is against the "
                 "2x2 block-averaged truth and is limited by the R/B sites sitting off the block centre.",
    }
    (out / "bench_decode.json").write_text(json.dumps(result, indent=1))

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for r in rows:
        ax.scatter(r["ms_per_mp"], r["psnr_db"], color="tab:red" if r["half_size"] else "tab:blue")
        ax.annotate(r["algorithm"], (r["ms_per_mp"], r["psnr_db"]), textcoords="offset points", xytext=(4, 3),
                    fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("decode time (ms per megapixel, log)")
    ax.set_ylabel("PSNR vs truth (dB)")
    ax.set_title(f"decode_raw: time vs error ({w}x{h} synthetic DNG)")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "bench_decode.png", dpi=120)
    print(f"wrote {out / 'bench_decode.json'} and {out / 'bench_decode.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
