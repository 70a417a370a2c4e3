"""The map's model and files: the similarity alignment recovers a known similarity, and a written map reads
back through :func:`ar_anchor.boards.read_layout` (both formats) equal to the map."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ar_anchor.boards import read_layout
from ar_anchor.config import BoardConfig
from ar_anchor.errors import InputError
from ar_anchor.geometry import Pose
from ar_anchor.tools.map import (
    MarkerMap,
    aligned_errors,
    rms_m,
    similarity_align,
    write_layout_toml,
    write_layout_yaml,
)
from ar_anchor.tools.map.command import MapOutputs


def a_map() -> MarkerMap:
    rng = np.random.default_rng(0)
    poses = {0: Pose.identity()}
    for marker_id in (3, 7, 12, 40):
        poses[marker_id] = Pose(rng.normal(0.0, 0.5, 3), rng.normal(0.0, 0.3, 3))
    return MarkerMap(0.0347, 0, poses)


def test_similarity_align_recovers_a_known_similarity():
    # given points and their image under a known scale, rotation and translation
    rng = np.random.default_rng(1)
    points = rng.normal(0.0, 1.0, (30, 3))
    rotation = Pose(np.array([0.3, -1.2, 2.0]), np.zeros(3)).rotation
    moved = 1.7 * points @ rotation.T + np.array([0.5, -2.0, 3.0])
    # when aligned
    alignment = similarity_align(points, moved)
    # then the similarity is recovered and maps the points exactly
    assert alignment.scale == pytest.approx(1.7, rel=1e-12)
    np.testing.assert_allclose(alignment.rotation, rotation, atol=1e-12)
    np.testing.assert_allclose(alignment.apply(points), moved, atol=1e-12)
    assert similarity_align(points, moved, with_scale=False).scale == 1.0


def test_aligned_errors_of_a_mirrored_map_are_not_hidden():
    # given a map and its mirror image (a reflection is no similarity: the planar flip of a whole map)
    truth = a_map().all_corners()
    mirrored = {i: c * np.array([1.0, 1.0, -1.0]) for i, c in truth.items()}
    # then the alignment keeps a proper rotation and the error stays large
    alignment, residuals = aligned_errors(mirrored, truth)
    assert np.linalg.det(alignment.rotation) == pytest.approx(1.0)
    assert rms_m(residuals) > 0.05
    _, exact = aligned_errors(truth, truth)
    assert rms_m(exact) < 1e-12


@pytest.mark.parametrize("suffix", [".yml", ".toml"])
def test_written_layouts_read_back_equal(tmp_path, suffix):
    # given a map
    marker_map = a_map()
    # when written to both formats (--out names one, the other is beside it)
    outputs = MapOutputs(tmp_path / f"layout{suffix}")
    write_layout_yaml(outputs.yaml, marker_map)
    write_layout_toml(outputs.toml, marker_map, "a header\nsecond line")
    # then the named file is --out, both read back equal to 1e-9, and as a custom board
    assert outputs.primary == tmp_path / f"layout{suffix}"
    assert {outputs.yaml.suffix, outputs.toml.suffix} == {".yml", ".toml"}
    assert outputs.report == tmp_path / "layout_report.md" and outputs.rrd == tmp_path / "layout.rrd"
    for path in (outputs.yaml, outputs.toml):
        layout = read_layout(path)
        assert [marker_id for marker_id, _ in layout] == marker_map.ids
        for marker_id, corners in layout:
            np.testing.assert_allclose(np.array(corners), marker_map.corners(marker_id), rtol=0, atol=1e-9)
        board = BoardConfig(name="map", kind="custom", layout=layout)
        assert board.marker_length_of(3) == pytest.approx(0.0347, abs=1e-9)
    assert outputs.yaml.read_text().startswith("%YAML:1.0") and "aruco_bc_mInfoType: 1" in outputs.yaml.read_text()


def test_out_must_name_a_layout_file(tmp_path):
    with pytest.raises(InputError, match=r"--out .*layout\.csv.*\.yml.*\.toml"):
        MapOutputs(tmp_path / "layout.csv")


@pytest.mark.realdata
def test_map_of_aruco_library_reads_as_ours(realdata):
    # the ArUco library's own marker map of the chessboard video's sheet reads as a layout too
    layout = read_layout(Path(realdata) / "aruco_testdata" / "chessboard" / "chessboardinfo_meters.yml")
    assert len(layout) == 18
