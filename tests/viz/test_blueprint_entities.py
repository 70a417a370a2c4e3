"""The run layout names only entities a run's recording has: every view's origin, and every entity its
contents rules name, is in the recording of a demo run (live-like, causal) or of an offline replay of it
(which adds the live filter's axes, ``world/causal``), drawn with overlay images."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest
import rerun.blueprint as rrb

from ar_anchor.camera import CameraModel
from ar_anchor.config import demo_config
from ar_anchor.run.loop import OfflineReplay, run_session
from ar_anchor.run.options import RunOptions
from ar_anchor.sources.synthetic import SyntheticSource
from ar_anchor.synthetic import demo_scene
from ar_anchor.track.tracker import Tracker
from ar_anchor.viz.blueprints import RUN_PLOTS, Framing, run_blueprint

RERUN = Path(sys.executable).with_name("rerun")


def _entities(path: Path) -> set[str]:
    """Every entity path with data in ``path``, and each of its parents."""
    printed = subprocess.run(
        [str(RERUN), "rrd", "print", str(path)], capture_output=True, text=True, timeout=120, check=True
    ).stdout
    entities = set()
    for line in printed.splitlines():
        if line.startswith("Chunk(") and " - data columns" in line:
            entity = line.split(") - ", 1)[1].split(" - data columns", 1)[0]
            parts = entity.strip("/").split("/")
            entities.update("/".join(parts[: i + 1]) for i in range(len(parts)))
    return entities


def _views(container) -> list:
    if isinstance(container, rrb.View):
        return [container]
    return [view for child in container.contents for view in _views(child)]


def _named(view) -> list[str]:
    """The entities a view names: its origin and each contents rule's path (wildcards and $origin resolved)."""
    rules = [view.contents] if isinstance(view.contents, str) else list(view.contents)
    named = [str(view.origin).strip("/")]
    for rule in rules:
        pattern = rule[2:] if rule[:2] in ("+ ", "- ") else rule
        pattern = pattern.replace("$origin", str(view.origin)).strip().removesuffix("/**").strip("/")
        if pattern:
            named.append(pattern)
    return named


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> set[str]:
    if not RERUN.exists():
        pytest.skip(f"{RERUN} not found")
    root = tmp_path_factory.mktemp("runs")
    config = demo_config()
    config = dataclasses.replace(config, recording=dataclasses.replace(config.recording, overlay_images=True))
    scene = demo_scene(config, CameraModel.from_fov(480, 360, 70.0), frames=40)
    entities: set[str] = set()
    for name, offline in (("causal", None), ("offline", OfflineReplay(lambda: SyntheticSource(scene)))):
        with SyntheticSource(scene) as source:
            result = run_session(source, Tracker(config, scene.camera), root / name, RunOptions(), offline=offline)
        entities |= _entities(result.recording_rrd)
    return entities


@pytest.mark.slow
def test_every_entity_the_run_layout_names_is_in_a_runs_recording(recorded):
    framed = Framing.on([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0]], [0.05, 0.1], [0.1, 0.0, 1.0])
    for blueprint in (run_blueprint(), run_blueprint(overlay_image=True, framing=framed)):
        for view in _views(blueprint.root_container):
            for entity in _named(view):
                assert entity in recorded, f"view {view.name!r} names {entity!r}, which no recording has"


@pytest.mark.slow
def test_each_plot_has_series_in_the_recording(recorded):
    for origin, title in RUN_PLOTS:
        assert any(entity.startswith(origin + "/") for entity in recorded), (title, origin)


def test_the_3d_eye_is_framed_on_the_targets_from_the_cameras_side():
    # given two markers 0.4 m apart and a camera 1 m in front of them
    framing = Framing.on([[-0.2, 0.0, 0.0], [0.2, 0.0, 0.0]], [0.05, 0.05], [0.0, 0.0, 1.0])
    eye, target = (tuple(framing.eye), tuple(framing.target))
    # then the eye looks at their middle, from the camera's side, near enough to tell them apart
    assert target == pytest.approx((0.0, 0.0, 0.0))
    distance = sum(c * c for c in eye) ** 0.5
    assert 0.5 < distance < 1.0 and eye[2] > 0.5
    # and a lone 5 cm marker is framed closer than the camera sees it from, not lost as a dot
    lone = Framing.on([[0.0, 0.0, 0.0]], [0.05], [0.0, 0.0, 2.0])
    assert sum(c * c for c in lone.eye) ** 0.5 < 0.3
