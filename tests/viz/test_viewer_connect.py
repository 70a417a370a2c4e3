"""The viewer process: --spawn starts one of its own (never another's), --connect checks the address first."""

from __future__ import annotations

import socket

import pytest

from ar_anchor.errors import InputError
from ar_anchor.viz import viewer


class _FakeViewer:
    """Stands in for ``subprocess.Popen`` of the viewer: listens on the port of its command line."""

    started: list[list[str]] = []

    def __init__(self, command, **_kwargs) -> None:
        type(self).started.append(command)
        self.server = socket.create_server(("127.0.0.1", int(command[command.index("--port") + 1])))

    def poll(self) -> None:
        return None


@pytest.fixture
def fake_viewer(monkeypatch):
    monkeypatch.setenv("DISPLAY", ":0")
    monkeypatch.setattr(viewer, "_viewer_executable", lambda: "rerun")
    monkeypatch.setattr(viewer.subprocess, "Popen", _FakeViewer)
    _FakeViewer.started = []
    return _FakeViewer


def test_spawn_does_not_stream_into_a_viewer_that_already_listens(monkeypatch, fake_viewer):
    # given something (another user's viewer) listening on the default port
    with socket.create_server(("127.0.0.1", 0)) as other:
        monkeypatch.setattr(viewer, "VIEWER_PORT", other.getsockname()[1])
        # when a run asks for --spawn
        url = viewer.spawn_local_viewer()
    # then it started its own viewer, on another port, and streams there
    assert len(fake_viewer.started) == 1
    port = int(fake_viewer.started[0][fake_viewer.started[0].index("--port") + 1])
    assert port != viewer.VIEWER_PORT
    assert url == f"rerun+http://127.0.0.1:{port}/proxy"
    assert fake_viewer.started[0][fake_viewer.started[0].index("--bind") + 1] == "127.0.0.1"


def test_spawn_uses_the_default_port_when_it_is_free(monkeypatch, fake_viewer):
    with socket.create_server(("127.0.0.1", 0)) as probe:
        free = probe.getsockname()[1]
    monkeypatch.setattr(viewer, "VIEWER_PORT", free)
    assert viewer.spawn_local_viewer() == f"rerun+http://127.0.0.1:{free}/proxy"


def test_a_viewer_that_dies_at_start_is_not_waited_for(monkeypatch, fake_viewer, caplog):
    class Dead:
        def __init__(self, command, **_kwargs) -> None:
            pass

        def poll(self) -> int:
            return 1

    monkeypatch.setattr(viewer.subprocess, "Popen", Dead)
    monkeypatch.setattr(viewer, "_START_TIMEOUT_S", 60.0)
    assert viewer.spawn_local_viewer() is None
    assert "did not start listening" in caplog.text


def test_connect_passes_when_a_viewer_listens():
    with socket.create_server(("127.0.0.1", 0)) as server:
        viewer.require_viewer(f"rerun+http://127.0.0.1:{server.getsockname()[1]}/proxy")


def test_connect_to_nothing_names_the_option_and_the_address():
    with socket.create_server(("127.0.0.1", 0)) as probe:
        port = probe.getsockname()[1]
    with pytest.raises(InputError, match=rf"^--connect rerun\+http://127\.0\.0\.1:{port}/proxy: .*127\.0\.0\.1:{port}"):
        viewer.require_viewer(f"rerun+http://127.0.0.1:{port}/proxy")


def test_a_viewer_url_without_a_port_means_rerun_s_port():
    assert viewer.viewer_address("rerun+http://example.org/proxy") == ("example.org", viewer.VIEWER_PORT)
