"""The release page (manifests.page) on the tiny release: thumbnails, links, accuracy, failures, relighting set."""
from __future__ import annotations

import os
import re
from urllib.parse import unquote

import numpy as np

from manifests import open_release, verify_release, write_table
from manifests.page import accuracy_rows, page_html, thumbnail_picture, write_release_page
from pipeline.codecs.image import read_png


def _links(text: str) -> list[str]:
    return [unquote(v) for v in re.findall(r'(?:href|src)="([^"#][^"]*)"', text)]


def test_page_links_labelled_thumbnails_of_every_map_and_verifies(release_dir, tiny):
    from manifests import append_rows, asset_row
    from pipeline.codecs.exr import write_exr

    relit = write_exr(release_dir / "actions" / "A0000" / "renders" / "N000" / "procedural_sky.exr",
                      np.full((tiny.H, tiny.W, 4), 0.5, np.float32))
    append_rows(release_dir, "assets", [asset_row(release_dir, relit, "relit_procedural_sky", "A0000", "N000")])
    page = write_release_page(release_dir)
    text = page.read_text()
    for cam in tiny.CAMS:
        for kind in ("full_on", "pos", "neg", "normal_alpha", "albedo", "mask"):
            assert f"cam {cam} · {kind}" in text
            thumb = release_dir / "page" / "A0000" / f"{kind}_{cam}.png"
            assert thumb.is_file() and read_png(thumb).shape == (tiny.H, tiny.W, 3)
            assert f'href="actions/A0000/{kind}/{cam}.' in text  # the thumbnail links to the file itself
    assert all((release_dir / link).is_file() for link in _links(text))
    assert "Not evaluated" in text and "http" not in text.replace("http-equiv", "")
    kinds = open_release(release_dir).assets.kind.value_counts()
    assert kinds["page"] == 1 and kinds["page_thumbnail"] == 13
    assert "view N000 · procedural_sky" in text
    # the thumbnails are listed per camera, yet the action's cameras are the captured ones only
    assert open_release(release_dir).action("A0000").cameras == list(tiny.CAMS)
    assert verify_release(release_dir).ok


def test_page_shows_accuracy_failures_and_rewrites_only_stale_thumbnails(release_dir):
    write_table(release_dir, "metrics", [
        dict(action_id="A0000", camera_id=c, metric="normal_mean_deg", region="valid", value=v, unit="deg",
             source="evaluate", run_id="r1") for c, v in (("00000", 4.0), ("00001", 6.0))])
    write_table(release_dir, "metrics_summary", [dict(metric="normal_mean_deg", value=4.9, unit="deg",
                                                      aggregation="pooled", n_actions=1, source="evaluate",
                                                      run_id="r1")])
    rows = open_release(release_dir).table("actions").to_pylist()
    rows.append(rows[0] | {"action_id": "A0009", "status": "failed", "error": "decode: <capture>/x.dng: truncated"})
    write_table(release_dir, "actions", rows)
    write_release_page(release_dir)
    thumb = release_dir / "page" / "A0000" / "full_on_00000.png"
    os.utime(thumb, (1, 1))
    text = write_release_page(release_dir).read_text()
    assert "<code>normal_mean_deg</code></td><td>deg</td><td class=\"num\">4.900</td><td class=\"num\">5.000</td>" in text
    assert "Failed actions" in text and "decode: &lt;capture&gt;/x.dng: truncated" in text
    assert thumb.stat().st_mtime > 1  # older than its source: made again
    assert verify_release(release_dir).ok


def test_a_thumbnail_that_fails_raises_and_leaves_the_previous_page(release_dir):
    """The thumbnails are written on a thread pool: the first one that fails raises from write_release_page,
    naming its file, and the page is not replaced."""
    import pytest

    page = write_release_page(release_dir)
    before = page.read_bytes()
    for thumb in (release_dir / "page").rglob("*.png"):
        thumb.unlink()  # made again from their sources, one of which is now unreadable
    broken = release_dir / "actions" / "A0000" / "albedo" / "00001.exr"
    broken.write_bytes(b"not an EXR file")
    with pytest.raises(Exception, match=r"00001\.exr"):
        write_release_page(release_dir)
    assert page.read_bytes() == before
    assert not list(release_dir.glob(".index.html.*.tmp"))
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="threads"):
            write_release_page(release_dir, threads=bad)


def test_relighting_set_grid_with_split_and_environment_labels(release_dir):
    example = {"example_id": "A0000_03", "split": "test", "environment_name": "studio_small_03_1k",
               "image_png": "relight/A0000_03/image.png", "albedo_png": "relight/A0000_03/albedo.png",
               "normal_png": "relight/A0000_03/normal.png"}
    rel = open_release(release_dir)
    text = page_html(release_dir, rel.table("actions").to_pylist(), rel.table("assets").to_pylist(), [], [],
                     [example], {}, lambda source, kind, out: out)
    assert "Relighting set" in text and "A0000_03 · test · studio_small_03_1k" in text
    for name in ("image", "albedo", "normal"):
        assert f'src="relight/A0000_03/{name}.png"' in text
    without = page_html(release_dir, rel.table("actions").to_pylist(), [], [], [], [], {}, lambda s, k, o: o)
    assert "Relighting set" not in without


def test_accuracy_rows_put_the_release_value_beside_each_actions_mean():
    summary = [dict(metric="chamfer_mm", value=3.0, unit="mm", aggregation="mean_over_actions")]
    metrics = [dict(metric="chamfer_mm", unit="mm", action_id=a, value=v, source="evaluate")
               for a, v in (("A0", 2.0), ("A1", 4.0))] + [
        dict(metric="photometric_valid_fraction", unit="1", action_id="A0", value=0.5, source="photometric")]
    rows = accuracy_rows(summary, metrics, ["A0", "A1"])
    assert rows == [{"metric": "chamfer_mm", "unit": "mm", "aggregation": "mean_over_actions", "release": 3.0,
                     "per_action": {"A0": 2.0, "A1": 4.0}}]


def test_thumbnails_of_normals_are_black_where_alpha_is_zero():
    data = np.zeros((4, 6, 4), np.float32)
    data[..., 2] = 1.0
    data[:2, :, 3] = 1.0
    pic = thumbnail_picture("normal_alpha", data)
    assert pic.dtype == np.uint8 and pic.shape == (4, 6, 3)
    assert (pic[2:] == 0).all() and (pic[:2, :, 2] == 255).all()


def test_thumbnails_of_linear_maps_average_in_linear_light():
    """Columns of albedo 0 and 1 shrunk to half the width: each thumbnail pixel is their linear mean 0.5, sRGB
    encoded (0.7354 -> 188), not the mean of the encoded values (0 and 255 -> 128); a radiance map keeps the
    exposure of its whole map's 99th percentile (here 1.0 -> 0.9 -> sRGB 0.9546 -> 243 for a pixel of 1)."""
    stripes = np.zeros((2, 4, 3), np.float32)
    stripes[:, 1::2] = 1.0
    pic = thumbnail_picture("albedo", stripes, width=2)
    assert pic.shape == (1, 2, 3) and (pic == 188).all()
    ones = np.ones((4, 8, 3), np.float32)
    assert (thumbnail_picture("full_on", ones, width=4) == 243).all()
