"""Optional dependencies: a command that needs an extra says which one, not an ImportError."""

from __future__ import annotations

import importlib.util

from ar_anchor.cli.main import main


def test_study_without_matplotlib_names_the_extra(tmp_path, monkeypatch, capsys):
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "matplotlib" else real(name, *a))
    code = main(["study", "outliers", "--quick", "--out", str(tmp_path / "study")])
    err = capsys.readouterr().err
    assert code == 2
    assert "ar-anchor[study]" in err and "Traceback" not in err
    assert not (tmp_path / "study").exists()
