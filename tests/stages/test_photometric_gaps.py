"""The photometric stage's finalize opens the filled holes the views see through, or whose gradient ratios are the
backdrop's, in every map it wrote."""
from __future__ import annotations

import json

import numpy as np

from artifacts.layout import ArtifactWriter
from pipeline.codecs.exr import read_exr, write_exr
from pipeline.codecs.image import mask_from_png, read_png, write_png
from pipeline.stage import StageContext
from stages.numerics.gaps import GapConfig
from stages.photometric import PhotometricConfig, open_gaps, write_gaps_sheet
from tests.unit.numerics.test_gaps import (BLOCK, FRAME, SIZE, block_slit, box_mask, filled, gradient_images,
                                           ring_cameras)


def _stage_folder(tmp_path, boxes, patch_in=None):
    """A photometric task's folder after its views ran (filled masks, their holes, flat maps) and its decode
    upstream (the cameras and the gradient images), for the 12 ring cameras looking at ``boxes``. ``patch_in``:
    camera id -> (H, W) bool, a hole the mask step left in that view (a dark patch, or a slit only it sees
    through), filled like the others; its gradient images show a surface there unless the key ends in ``:slit``."""
    cams = ring_cameras()
    ids = [f"{i:05d}" for i in range(len(cams))]
    decode = tmp_path / "decode"
    for product in ("pos", "neg"):
        (decode / product).mkdir(parents=True)
    (decode / "cameras.json").write_text(json.dumps({"cameras": [
        {"camera_id": cid, "K": K.tolist(), "cam_from_world": T.tolist(), "width": SIZE, "height": SIZE}
        for cid, (K, T) in zip(ids, cams)]}))
    out = ArtifactWriter("photometric", tmp_path / "out")
    holes, stats = {}, {}
    patches = {key.split(":")[0]: (value, key.endswith(":slit")) for key, value in (patch_in or {}).items()}
    for cid, (K, T) in zip(ids, cams):
        mask, hole = filled(box_mask(K, T, boxes))
        shown = mask & ~hole
        if cid in patches:
            patch, slit = patches[cid]
            hole = hole | (patch & mask)
            shown = shown & ~patch if slit else shown
        pos, neg = gradient_images(shown)
        write_exr(decode / "pos" / f"{cid}.exr", pos)
        write_exr(decode / "neg" / f"{cid}.exr", neg)
        for product in ("normal_alpha", "albedo", "mask", "filled_holes", "normal_preview"):
            out.path(product, cid).parent.mkdir(parents=True, exist_ok=True)
        normal_alpha = np.zeros((SIZE, SIZE, 4), np.float32)
        normal_alpha[mask] = [0.0, 0.0, 1.0, 0.9]
        write_exr(out.path("normal_alpha", cid), normal_alpha)
        write_exr(out.path("albedo", cid), np.where(mask[..., None], np.full(3, 0.5, np.float32), np.float32(0.0)))
        write_png(out.path("mask", cid), mask)
        write_png(out.path("albedo_preview", cid), np.full((SIZE, SIZE, 3), 128, np.uint8))
        if hole.any():
            write_png(out.path("filled_holes", cid), hole)
        holes[cid] = hole
        stats[cid] = {"mask_fraction": float(mask.mean()), "valid_fraction": 1.0}
    ctx = StageContext(stage="photometric", scope_id="A0000", session_id="S000", action_id="A0000",
                       out_dir=tmp_path / "out", upstream={"decode": decode}, raw_inputs={}, rig={},
                       capture_root=tmp_path)
    return ctx, out, holes, stats


def test_finalize_opens_the_frame_in_mask_normals_albedo_and_stats(tmp_path):
    ctx, out, holes, stats = _stage_folder(tmp_path, FRAME)
    record = open_gaps(ctx, PhotometricConfig(), stats)
    seen_through = [cid for cid, h in holes.items() if h.sum() >= 20]
    assert record["gaps"] >= len(seen_through) >= 4 and record["opened_pixels"] >= sum(
        int(holes[c].sum()) for c in seen_through)
    assert record["gaps"] == record["gaps_seen_through"] + record["gaps_by_ratio"]
    for cid in seen_through:
        mask = mask_from_png(read_png(out.path("mask", cid)))
        normal_alpha = read_exr(out.path("normal_alpha", cid))
        albedo = read_exr(out.path("albedo", cid))
        assert not mask[holes[cid]].any()
        assert (normal_alpha[holes[cid]] == 0).all() and (albedo[holes[cid]] == 0).all()
        assert (normal_alpha[mask, 3] <= 0.9).all() and (normal_alpha[mask, 3] == 0.25).any()  # the new rim
        assert stats[cid]["gap_pixels"] == holes[cid].sum() and stats[cid]["valid_fraction"] < 1.0
        assert out.path("normal_preview", cid).is_file()
    sheet = read_png(out.path("gaps_sheet"))  # a tile per view with holes, four to a row
    assert sheet.shape == (-(-record["holes"] // 4) * SIZE, 4 * SIZE, 3)
    # a finalize run again (a lost worker) finds the masks opened and decides the same
    again = open_gaps(ctx, PhotometricConfig(), stats)
    assert {k: again[k] for k in ("holes", "gaps", "opened_pixels")} == {
        k: record[k] for k in ("holes", "gaps", "opened_pixels")}


def test_finalize_leaves_a_block_without_holes_and_can_be_turned_off(tmp_path):
    ctx, out, holes, stats = _stage_folder(tmp_path / "block", BLOCK)
    assert not any(h.any() for h in holes.values())
    assert open_gaps(ctx, PhotometricConfig(), stats) == {"enabled": True, "holes": 0, "gaps": 0, "opened_pixels": 0}
    ctx, out, holes, stats = _stage_folder(tmp_path / "frame", FRAME)
    before = {cid: read_png(out.path("mask", cid)) for cid in holes}
    off = PhotometricConfig(gaps=GapConfig(enabled=False))
    assert open_gaps(ctx, off, stats) == {"enabled": False}
    assert all(np.array_equal(read_png(out.path("mask", cid)), before[cid]) for cid in holes)


def test_a_dark_patch_one_view_leaves_stays_filled_a_slit_it_sees_through_opens(tmp_path):
    """A hole in one view only: the views together cannot tell (no second view sees it); its gradient ratios can:
    a dark surface's stay filled, the backdrop's open."""
    ctx, out, holes, stats = _stage_folder(tmp_path / "patch", BLOCK, {"00003": block_slit()})
    record = open_gaps(ctx, PhotometricConfig(), stats)
    assert record["holes"] == 1 and record["gaps"] == 0 and record["opened_pixels"] == 0
    assert mask_from_png(read_png(out.path("mask", "00003")))[block_slit()].all()
    ctx, out, holes, stats = _stage_folder(tmp_path / "slit", BLOCK, {"00003:slit": block_slit()})
    record = open_gaps(ctx, PhotometricConfig(), stats)
    assert (record["holes"], record["gaps_seen_through"], record["gaps_by_ratio"]) == (1, 0, 1)
    assert record["opened_pixels"] == block_slit().sum()
    assert not mask_from_png(read_png(out.path("mask", "00003")))[block_slit()].any()
    assert (read_exr(out.path("normal_alpha", "00003"))[block_slit()] == 0).all()
    # the ratio test off: the views alone leave it filled
    ctx, out, holes, stats = _stage_folder(tmp_path / "slit_off", BLOCK, {"00003:slit": block_slit()})
    off = PhotometricConfig(gaps=GapConfig(backdrop_ratio_max=0.0))
    assert open_gaps(ctx, off, stats)["opened_pixels"] == 0


def test_gaps_sheet_paints_opened_holes_red_and_kept_ones_blue(tmp_path):
    out = ArtifactWriter("photometric", tmp_path)
    out.path("albedo_preview", "00000").parent.mkdir(parents=True)
    for cid in ("00000", "00001"):
        write_png(out.path("albedo_preview", cid), np.full((200, 200, 3), 100, np.uint8))
    hole = np.zeros((200, 200), bool)
    hole[150:170, 100:130] = True  # 600 px, clear of the label in the top-left corner
    none = np.zeros_like(hole)
    write_gaps_sheet(out, ["00000", "00001", "00002"], [hole, hole, none], [hole, none, none])
    sheet = read_png(out.path("gaps_sheet"))
    assert sheet.shape == (200, 800, 3)  # two views with holes, a row of four tiles
    red = (sheet[..., 0] > 150) & (sheet[..., 1] < 100) & (sheet[..., 2] < 100)
    blue = (sheet[..., 2] > 150) & (sheet[..., 0] < 100)
    assert red[:, :200].sum() == 600 and not red[:, 200:].any()
    assert blue[:, 200:400].sum() == 600 and not blue[:, :200].any()
