"""Security: input files are data, never code; runs write only where they were told to; rerun servers
listen on localhost.

1. A static AST walk over every module of the package: no ``eval``/``exec``/``compile``, no pickle,
   marshal, shelve or unsafe YAML loaders, no ``shell=True``, ``os.system`` or ``os.popen``, no
   ``np.load(allow_pickle=True)``, no imports by computed name (audited exceptions: the lazy exports and
   ``lazy.import_held``, whose module names are literals at every call), pickle only in
   the offline replay's spool (audited: its own unnamed temporary file, read back by an unpickler that
   admits the package's classes and numpy arrays only, tested below). Plus files
   written to look like code (YAML ``!!python`` tags, a TOML with a Python payload) stay inert.
2. Paths in configs (mesh files, board layouts) resolve relative to the config file, are only read,
   and every file a run creates or changes is inside its output directory (or the one file the
   user named, like ``--video-out``).
3. rerun: the SDK serves nothing (``rr.serve_grpc`` / ``rr.serve_web_viewer`` bind every interface); the viewers
   the package starts (``--spawn``, ``--serve``, ``ar-anchor view``) listen on localhost only, unless the user
   gives ``view --bind`` (rerun 0.41's ``rr.spawn`` starts ``rerun`` with its default bind, 0.0.0.0, so the
   package starts the viewer itself).
"""

from __future__ import annotations

import ast
import functools
import hashlib
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from ar_anchor.boards import read_layout
from ar_anchor.camera import CameraModel
from ar_anchor.config import load_config
from ar_anchor.errors import CameraError, ConfigError
from ar_anchor.render.models import MESH_SUFFIXES, load_mesh
from tests.helpers import assert_clean_exit, run_main

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "ar_anchor"
MODULES = sorted(PACKAGE.rglob("*.py"))


@functools.cache
def parsed(path: Path) -> ast.Module:
    return ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


# ============================================================================ 1. data, never code

FORBIDDEN_CALLS = {
    "eval": "evaluates text as code",
    "exec": "executes text as code",
    "compile": "compiles text to code",
    "__import__": "imports a module by computed name",
    "os.system": "runs a shell command",
    "os.popen": "runs a shell command",
    "os.exec*": "replaces the process with a command",
    "pickle.load": "unpickling runs code",
    "pickle.loads": "unpickling runs code",
    "pickle.Unpickler": "unpickling runs code",
    "marshal.loads": "loads code objects",
    "marshal.load": "loads code objects",
    "shelve.open": "a pickle store",
    "yaml.load": "PyYAML's load (use safe_load)",
    "yaml.unsafe_load": "constructs arbitrary objects",
    "yaml.full_load": "constructs Python objects",
    "yaml.load_all": "PyYAML's load_all (use safe_load_all)",
    "yaml.unsafe_load_all": "constructs arbitrary objects",
    "jsonpickle.decode": "a pickle in JSON",
    "dill.load": "unpickling runs code",
    "dill.loads": "unpickling runs code",
    "torch.load": "unpickles by default",
    "joblib.load": "unpickles",
}
FORBIDDEN_IMPORTS = {"pickle", "cPickle", "_pickle", "marshal", "shelve", "dill", "cloudpickle", "jsonpickle"}
# (module, enclosing function) -> why a dynamic import there is safe
AUDITED = {
    ("ar_anchor/__init__.py", "__getattr__"): "lazy exports: the module name comes from the fixed _EXPORTS table",
    ("ar_anchor/lazy.py", "__getattr__"): "lazy exports: the module comes from the package's fixed table (every "
    "lazy_exports call passes a literal one: checked below)",
    ("ar_anchor/lazy.py", "import_held"): "every import_held call passes a literal module name (checked below)",
}


# module -> why pickle there is safe (its imports and calls are allowed in that module only)
PICKLE_AUDITED = {
    "ar_anchor/track/spool.py": "the offline replay's spool: an unnamed temporary file the run wrote itself, "
    "never input, read back by _SpoolUnpickler (the package's classes and numpy arrays only)",
}


def _dotted(node: ast.AST) -> str:
    """``a.b.c`` for a Name/Attribute chain ('' for anything else)."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        base = _dotted(node.value)
        return f"{base}.{node.attr}" if base else ""
    return ""


def _aliases(tree: ast.AST) -> dict[str, str]:
    """Local name -> what it was imported as (``import numpy as np`` -> np: numpy; ``from os import
    system`` -> system: os.system), so that renamed imports cannot hide a forbidden call."""
    names = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                names[alias.asname or alias.name.split(".")[0]] = (
                    alias.name if alias.asname else alias.name.split(".")[0]
                )
        elif isinstance(node, ast.ImportFrom) and node.module:
            for alias in node.names:
                names[alias.asname or alias.name] = f"{node.module}.{alias.name}"
    return names


def _resolve(name: str, aliases: dict[str, str]) -> str:
    head, _, rest = name.partition(".")
    full = aliases.get(head, head)
    return f"{full}.{rest}" if rest else full


class _Finder(ast.NodeVisitor):
    def __init__(self, path: Path, tree: ast.AST) -> None:
        self.path = path.relative_to(REPO).as_posix()
        self.aliases = _aliases(tree)
        self.function: list[str] = []
        self.problems: list[str] = []

    def report(self, node: ast.AST, text: str) -> None:
        self.problems.append(f"{self.path}:{getattr(node, 'lineno', '?')}: {text}")

    def visit_FunctionDef(self, node: ast.FunctionDef) -> None:
        self.function.append(node.name)
        self.generic_visit(node)
        self.function.pop()

    visit_AsyncFunctionDef = visit_FunctionDef  # noqa: N815

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            if alias.name == "pickle" and self.path in PICKLE_AUDITED:
                continue
            if alias.name.split(".")[0] in FORBIDDEN_IMPORTS:
                self.report(node, f"imports {alias.name}")
        self.generic_visit(node)

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        if node.module and node.module.split(".")[0] in FORBIDDEN_IMPORTS:
            self.report(node, f"imports from {node.module}")
        self.generic_visit(node)

    def visit_Call(self, node: ast.Call) -> None:
        name = _resolve(_dotted(node.func), self.aliases)
        audited = (self.path, self.function[-1] if self.function else "") in AUDITED
        for forbidden, why in FORBIDDEN_CALLS.items():
            if forbidden.startswith("pickle.") and self.path in PICKLE_AUDITED:
                continue
            if name == forbidden or (forbidden.endswith("*") and name.startswith(forbidden[:-1])):
                self.report(node, f"calls {name}: {why}")
        if name in ("importlib.import_module",) and not isinstance(node.args[0], ast.Constant) and not audited:
            self.report(node, "imports a module by computed name")
        if name.rsplit(".", 1)[-1] == "import_held" and not (node.args and isinstance(node.args[0], ast.Constant)):
            self.report(node, "import_held of a computed name")
        if name.rsplit(".", 1)[-1] == "lazy_exports":
            table = node.args[1] if len(node.args) > 1 else None
            if not isinstance(table, ast.Dict) or not all(
                isinstance(key, ast.Constant) and isinstance(value, ast.List | ast.Tuple)
                for key, value in zip(table.keys, table.values)
            ):
                self.report(node, "lazy_exports of a computed table")
        keywords = {k.arg: k.value for k in node.keywords if k.arg}
        if name.startswith("subprocess.") or name.startswith("asyncio.create_subprocess"):
            shell = keywords.get("shell")
            if shell is not None and not (isinstance(shell, ast.Constant) and shell.value is False):
                self.report(node, f"{name} with shell={ast.unparse(shell)}")
            if node.args and isinstance(node.args[0], (ast.Constant, ast.JoinedStr)):
                self.report(node, f"{name} given a command string (a shell would split it): pass a list")
        if name in ("numpy.load", "np.load"):
            pickle = keywords.get("allow_pickle")
            if pickle is not None and not (isinstance(pickle, ast.Constant) and pickle.value is False):
                self.report(node, "numpy.load with allow_pickle")
        self.generic_visit(node)


def test_the_package_never_runs_input_as_code():
    assert len(MODULES) > 10, "the package was not found"
    problems = []
    for path in MODULES:
        tree = parsed(path)
        finder = _Finder(path, tree)
        finder.visit(tree)
        problems += finder.problems
    assert not problems, "\n".join(problems)


def test_the_offline_spool_reads_back_only_the_package_s_own_objects(tmp_path):
    from ar_anchor.geometry import Pose
    from ar_anchor.targets import TargetId
    from ar_anchor.track.spool import SpoolStore

    with SpoolStore(tmp_path) as spool:
        spool.append({TargetId.marker(3): Pose(np.ones(3), np.zeros(3))})
        spool.append(os.system)  # what a planted payload would need: a callable from outside the package
        spool.append(subprocess.Popen)
        ((name, pose),) = spool[0].items()
        assert isinstance(name, TargetId) and name == "marker:3" and np.array_equal(pose.rvec, np.ones(3))
        for position in (1, 2):
            with pytest.raises(Exception, match="the offline spool holds no"):
                spool[position]
    assert list(tmp_path.iterdir()) == []  # an unnamed file: nothing left behind, nothing another process can open


def test_the_ast_check_catches_what_it_should():
    # the checker itself, on code that does all the forbidden things (renamed imports included)
    source = (
        "import pickle as p\nimport os\nfrom os import system as run\nimport subprocess as sp\nimport yaml\n"
        "import numpy as np\nimport importlib\n"
        "def f(text, name):\n"
        "    eval(text); exec(text); p.loads(text); run('ls'); os.popen('ls'); yaml.load(text)\n"
        "    sp.run('ls -l'); sp.Popen(['ls'], shell=True); np.load(text, allow_pickle=True)\n"
        "    importlib.import_module(name); __import__(name); os.execv('/bin/sh', [])\n"
    )
    fake = PACKAGE / "evil_example.py"
    tree = ast.parse(source)
    finder = _Finder(fake, tree)
    finder.visit(tree)
    found = "\n".join(finder.problems)
    for text in ("imports pickle", "calls eval", "calls exec", "calls pickle.loads", "calls os.system", "os.popen",
                 "calls yaml.load", "command string", "shell=True", "allow_pickle", "computed name",
                 "calls __import__", "os.execv"):  # fmt: skip
        assert text in found, f"{text!r} not reported:\n{found}"


PAYLOAD = "touch {marker}"  # what each "code" file would do if it were ever executed


@pytest.mark.parametrize(
    ("kind", "text"),
    [
        pytest.param(
            "camera", "%YAML:1.0\n---\nimage_width: !!python/object/apply:os.system ['{cmd}']\n", id="yaml-tag"
        ),
        pytest.param(
            "camera",
            "image_width: 640\nimage_height: 480\ncamera_matrix: !!python/object/apply:os.system ['{cmd}']\n",
            id="ros-yaml-tag",
        ),
        pytest.param(
            "layout", "%YAML:1.0\n---\naruco_bc_markers: !!python/object/apply:os.system ['{cmd}']\n", id="map-tag"
        ),
        pytest.param("config", "[markers]\nlength_m = \"__import__('os').system('{cmd}')\"\n", id="toml-string"),
        pytest.param("config", "[[overlays]]\nkind = 'mesh'\npath = '$(`{cmd}`).obj'\n", id="toml-shell-path"),
        pytest.param("mesh", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nmtllib `{cmd}`.mtl\n", id="obj-mtllib"),
    ],
)
def test_code_shaped_input_files_stay_inert(tmp_path, kind, text):
    marker = tmp_path / "PWNED"
    path = tmp_path / {"camera": "cam.yml", "layout": "map.yml", "config": "c.toml", "mesh": "m.obj"}[kind]
    path.write_text(text.format(cmd=PAYLOAD.format(marker=marker)))
    try:
        if kind == "camera":
            CameraModel.from_yaml(path)
        elif kind == "layout":
            read_layout(path)
        elif kind == "config":
            from ar_anchor.render.overlay import OverlayRenderer

            OverlayRenderer(load_config(path), CameraModel.default_synthetic())
        else:
            load_mesh(path)
    except (CameraError, ConfigError):
        pass
    assert not marker.exists(), "an input file ran a command"


def test_mesh_formats_are_data_formats_only(tmp_path):
    # trimesh reads pickles (.npz / .pkl) and Python-scripted formats too; load_mesh takes data formats only
    assert set(MESH_SUFFIXES) <= {".obj", ".ply", ".stl", ".glb", ".gltf", ".off"}
    for suffix in (".npz", ".pkl", ".pickle", ".dae", ".3mf", ".py"):
        path = tmp_path / f"model{suffix}"
        path.write_bytes(b"\x80\x04K\x01.")  # a pickle of 1
        with pytest.raises(ConfigError, match="unsupported format"):
            load_mesh(path)


def test_a_gltf_cannot_make_the_loader_read_outside_its_folder(tmp_path):
    (tmp_path / "secret.bin").write_bytes(b"\0" * 36)
    folder = tmp_path / "models"
    folder.mkdir()
    path = folder / "escape.gltf"
    path.write_text('{"asset": {"version": "2.0"}, "buffers": [{"uri": "../secret.bin", "byteLength": 36}]}')
    with pytest.raises(ConfigError, match=r"mesh file .*escape\.gltf"):
        load_mesh(path)


# ============================================================================ 2. where runs read and write


def _snapshot(root: Path) -> dict[str, str]:
    """Every file under ``root`` with a digest of its content (what a run may have changed)."""
    files = {}
    for path in root.rglob("*"):
        if path.is_file():
            files[path.relative_to(root).as_posix()] = hashlib.sha256(path.read_bytes()).hexdigest()
    return files


def _changes(before: dict[str, str], after: dict[str, str]) -> set[str]:
    return {name for name, digest in after.items() if before.get(name) != digest} | (set(before) - set(after))


@pytest.fixture
def project(tmp_path) -> Path:
    """A project folder: configs in conf/ naming a mesh and a layout relative to themselves, media, a camera."""
    conf = tmp_path / "conf"
    (conf / "models").mkdir(parents=True)
    (conf / "boards").mkdir()
    (conf / "models" / "pin.obj").write_text("v 0 0 0\nv 0.01 0 0\nv 0 0.01 0\nv 0 0 0.01\nf 1 2 3\nf 1 2 4\n")
    (conf / "boards" / "pair.toml").write_text(
        "[[markers]]\nid = 20\ncorners = [[0, 0, 0], [0.05, 0, 0], [0.05, 0.05, 0], [0, 0.05, 0]]\n"
        "[[markers]]\nid = 21\ncorners = [[0.1, 0, 0], [0.15, 0, 0], [0.15, 0.05, 0], [0.1, 0.05, 0]]\n"
    )
    (conf / "tracker.toml").write_text(
        '[[boards]]\nname = "pair"\nkind = "custom"\nlayout = "boards/pair.toml"\n'
        '[[overlays]]\ntarget = "*"\nkind = "mesh"\npath = "models/pin.obj"\n'
    )
    images = tmp_path / "media"
    images.mkdir()
    for index in range(3):
        cv2.imwrite(str(images / f"f{index}.png"), np.full((48, 64, 3), 40 * index, np.uint8))
    CameraModel.from_fov(64, 48, 60.0).to_yaml(tmp_path / "cam64.yml")
    (tmp_path / "work").mkdir()  # the cwd of the runs, elsewhere than the config
    return tmp_path


def test_config_paths_resolve_relative_to_the_config_file(project):
    # given a cwd that is not the config's folder, and decoys where a cwd-relative lookup would look
    work = project / "work"
    (work / "models").mkdir()
    (work / "models" / "pin.obj").write_text("not a mesh at all\n")
    (work / "boards").mkdir()
    (work / "boards" / "pair.toml").write_text(
        "[[markers]]\nid = 7\ncorners = [[0, 0, 0], [0.05, 0, 0], [0.05, 0.05, 0], [0, 0.05, 0]]\n"
    )
    cwd = Path.cwd()
    os.chdir(work)
    try:
        config = load_config(Path("..") / "conf" / "tracker.toml")
    finally:
        os.chdir(cwd)  # and the models are read from another working directory
    overlay = config.overlays[0]
    assert Path(overlay.path).resolve() == (project / "conf" / "models" / "pin.obj").resolve()
    assert config.boards[0].marker_ids == (20, 21)  # conf/boards/pair.toml, not the decoy with marker 7
    assert len(load_mesh(overlay.path).faces) == 2  # the real mesh, not the decoy


@pytest.mark.parametrize(
    ("argv", "allowed"),
    [
        pytest.param(
            ["demo", "--frames", "2", "--config", "../conf/tracker.toml", "--out", "run"], ["work/run/"], id="demo"
        ),
        pytest.param(
            [
                "replay",
                "../media",
                "--camera",
                "../cam64.yml",
                "--config",
                "../conf/tracker.toml",
                "--out",
                "run",
                "--video-out",
                "clip.mp4",
            ],  # fmt: skip
            ["work/run/", "work/clip.mp4"],
            id="replay",
        ),
        pytest.param(
            [
                "live",
                "--device",
                "synthetic",
                "--camera",
                "../cam64.yml",
                "--config",
                "../conf/tracker.toml",
                "--max-frames",
                "2",
                "--record",
                "--out",
                "run",
            ],  # fmt: skip
            ["work/run/"],
            id="live-record",
        ),
        pytest.param(
            [
                "markers",
                "--board",
                "grid",
                "--cols",
                "2",
                "--rows",
                "1",
                "--size-mm",
                "30",
                "--gap-mm",
                "5",
                "--name",
                "pair",
                "--out",
                "sheets",
            ],  # fmt: skip
            ["work/sheets/"],
            id="markers",
        ),
        pytest.param(
            [
                "calibrate",
                "../media",
                "--charuco",
                "5x7",
                "--square-m",
                "0.04",
                "--marker-m",
                "0.03",
                "--dictionary",
                "DICT_4X4_50",
                "--out",
                "cal/cam.yml",
            ],  # fmt: skip
            ["work/cal/"],
            id="calibrate-failing",
        ),
    ],
)
def test_runs_write_only_inside_their_output(project, monkeypatch, argv, allowed):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    before = _snapshot(project)
    cwd = Path.cwd()
    os.chdir(project / "work")
    try:
        result = run_main(["-q", *argv])
    finally:
        os.chdir(cwd)
    assert_clean_exit(result)
    if argv[0] != "calibrate":  # no ChArUco board in these images: calibrate fails, cleanly
        assert result.code == 0, result.describe()
    changed = _changes(before, _snapshot(project))
    outside = sorted(name for name in changed if not any(name == a or name.startswith(a) for a in allowed))
    assert not outside, f"written outside {allowed}: {outside}"
    assert argv[0] == "calibrate" or changed, "the run wrote nothing at all"


# ============================================================================ 3. rerun servers

SERVING_CALLS = {"serve_grpc", "serve_web", "serve_web_viewer", "serve", "Server"}


def _rerun_calls(name: str) -> list[str]:
    """Calls to ``rerun.<name>`` (any import alias) in the package, as 'path:line'."""
    found = []
    for path in MODULES:
        tree = parsed(path)
        aliases = _aliases(tree)
        for node in ast.walk(tree):
            if isinstance(node, ast.Call):
                full = _resolve(_dotted(node.func), aliases)
                if full.startswith("rerun") and full.rsplit(".", 1)[-1] == name:
                    found.append(f"{path.relative_to(REPO)}:{node.lineno}")
    return found


def test_nothing_serves_rerun_over_the_network():
    # rerun 0.41's serve_grpc / serve_web bind every interface and take no bind address
    found = {name: _rerun_calls(name) for name in SERVING_CALLS}
    assert not any(found.values()), found


def test_viewer_command_lines_in_the_package_bind_localhost():
    # a viewer started by hand (["rerun", ..., "--bind", ADDRESS]) must name a loopback address
    for path in MODULES:
        tree = parsed(path)
        for node in ast.walk(tree):
            if isinstance(node, ast.List):
                items = [e.value if isinstance(e, ast.Constant) else None for e in node.elts]
                if "--bind" in items:
                    at = items.index("--bind") + 1
                    if _audited_bind(path, node, at):
                        continue
                    address = items[at] if at < len(items) else None
                    assert address in ("127.0.0.1", "localhost", "::1"), f"{path}:{node.lineno}: --bind {address}"


def _audited_bind(path: Path, node: ast.List, at: int) -> bool:
    """The one audited bind address that is not a constant: ``viewer._bind_option(address)``, whose callers
    pass LOOPBACK unless the user gave ``ar-anchor view --bind`` (warned about; tests/cli/test_view.py checks
    with ``ss`` that the default listens on 127.0.0.1 only)."""
    if path.relative_to(PACKAGE).as_posix() != "viz/viewer.py" or at >= len(node.elts):
        return False
    target = node.elts[at]
    return isinstance(target, ast.Name) and target.id == "address" and len(node.elts) == 2


def test_bind_addresses_other_than_loopback_come_from_the_user_only():
    from ar_anchor.cli.main import build_parser
    from ar_anchor.viz import viewer

    assert viewer.LOOPBACK == "127.0.0.1"
    assert viewer.serve_web_viewer.__kwdefaults__["bind"] == viewer.LOOPBACK
    assert viewer.open_native_viewer.__kwdefaults__["bind"] == viewer.LOOPBACK
    assert build_parser().parse_args(["view", "x.rrd"]).bind == viewer.LOOPBACK
    assert not hasattr(build_parser().parse_args(["demo", "--serve"]), "bind")  # --serve: loopback, always


def test_the_rerun_viewer_listens_on_all_interfaces_unless_told():
    # the premise of the xfail below, from the viewer's own help: its default bind address
    rerun = Path(sys.executable).with_name("rerun")
    if not rerun.exists():
        pytest.skip(f"{rerun} not found")
    help_text = subprocess.run([str(rerun), "--help"], capture_output=True, text=True, timeout=60).stdout
    assert "--bind" in help_text and "[default: 0.0.0.0]" in help_text


def test_spawn_starts_a_viewer_bound_to_localhost():
    # rr.spawn (rerun 0.41) has no bind parameter: any call to it exposes the viewer to the network
    assert not _rerun_calls("spawn"), f"rr.spawn used at {_rerun_calls('spawn')}"
