"""Bad input to the ``safemimic`` commands: one line on standard error naming the argument, exit
status 2, no traceback, and before any work (nothing evaluated, written or started).

The commands run in this process (:func:`safemimic.cli.main`), on real files in a temporary folder.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from safemimic.cli import main as safemimic
from shared.cli_args import check_output_path
from shared.config import load_config


def refused(capsys: pytest.CaptureFixture[str], *argv: str) -> str:
    """The one line a command that refuses ``argv`` prints on standard error (exit 2 asserted)."""
    assert safemimic(list(argv)) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    return err


def test_an_output_path_is_checked_for_what_it_must_be(tmp_path: Path) -> None:
    afile = tmp_path / "afile"
    afile.write_text("")
    check_output_path(tmp_path / "new" / "deeper", "--out", folder=True)  # created later: fine
    check_output_path(tmp_path, "--out", folder=True)
    check_output_path(tmp_path / "report.md", "--out", folder=False)
    with pytest.raises(ValueError, match="--out .*afile: exists and is not a folder"):
        check_output_path(afile, "--out", folder=True)
    with pytest.raises(ValueError, match="OUT.npz .*: .*afile is a file, not a folder"):
        check_output_path(afile / "x" / "y.npz", "OUT.npz", folder=False)
    with pytest.raises(ValueError, match="--out .*: is a folder, not a file name"):
        check_output_path(tmp_path, "--out", folder=False)
    assert not (tmp_path / "new").exists()  # a check creates nothing


def test_commands_refuse_an_output_path_they_cannot_write_before_any_work(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    afile = tmp_path / "afile"
    afile.write_text("")
    err = refused(capsys, "evaluate", "--scenario", "wave", "--seconds", "1", "--out", str(afile))
    assert err == f"safemimic evaluate: --out {afile}: exists and is not a folder"
    (tmp_path / "d.rrd").mkdir()
    err = refused(capsys, "evaluate", "--scenario", "wave", "--out", str(tmp_path), "--rrd", str(tmp_path / "d.rrd"))
    assert err.startswith("safemimic evaluate: --rrd ") and "is a folder" in err
    err = refused(capsys, "record-scenario", "wave", str(afile / "x.npz"))
    assert err.startswith("record-scenario: OUT.npz ") and "afile is a file, not a folder" in err
    err = refused(capsys, "record-scenario", "wave", str(tmp_path))
    assert "OUT.npz" in err and "is a folder" in err
    recording = tmp_path / "clip.npz"
    assert safemimic(["record-scenario", "wave", str(recording), "--seconds", "0.5"]) == 0
    capsys.readouterr()
    err = refused(capsys, "variants", str(recording), str(afile))
    assert err.endswith(f"OUT {afile}: exists and is not a folder")
    err = refused(capsys, "compare", str(tmp_path), str(tmp_path), "--out", str(tmp_path))
    assert err == f"safemimic compare: --out {tmp_path}: is a folder, not a file name"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile", "clip.npz", "d.rrd"]  # nothing written


def test_variants_refuse_a_file_that_is_no_npz_as_evaluate_does(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    for name, content in (("empty.npz", b""), ("text.npz", b"not a recording\n")):
        bad = tmp_path / name
        bad.write_bytes(content)
        by_variants = refused(capsys, "variants", str(bad), str(tmp_path / "out"))
        by_evaluate = refused(capsys, "evaluate", "--skeleton", str(bad), "--out", str(tmp_path / "eval"))
        assert f"{name}: cannot read as .npz: " in by_variants
        assert by_variants.split(f"{name}: ", 1)[1] == by_evaluate.split(f"{name}: ", 1)[1]
    assert not list((tmp_path / "out").glob("*"))


def test_placements_are_checked_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    clips = tmp_path / "clips"
    assert safemimic(["record-scenario", "wave", str(clips / "wave.npz"), "--seconds", "0.5"]) == 0
    capsys.readouterr()
    out = tmp_path / "out"
    err = refused(capsys, "evaluate", "--suite", str(clips), "--placements", "facing,garbage", "--out", str(out))
    assert err == ("safemimic evaluate: --placements: placement 'garbage': expected auto, side-by-side, facing, "
                   "recorded or x,y,yaw (m, m, rad)")
    err = refused(capsys, "evaluate", "--suite", str(clips), "--placements", "1,2", "--out", str(out))
    assert err.startswith("safemimic evaluate: --placements: placement '1,2': expected auto")
    err = refused(capsys, "evaluate", "--scenario", "wave", "--placement", "0,0,nan", "--out", str(out))
    assert err == "safemimic evaluate: --placement: placement '0,0,nan' is not finite"
    assert not out.exists()  # no summary, no run folder
    err = refused(capsys, "demo", "--placement", "garbage", "--no-rerun")
    assert err.startswith("safemimic demo: --placement: placement 'garbage': expected auto, side-by-side")
    assert "router:" not in capsys.readouterr().out  # nothing started


def test_an_x_y_yaw_placement_keeps_its_three_numbers_in_a_placements_list() -> None:
    from safemimic.evaluate.suite import _placements

    assert _placements("facing, 0.8,-0.5,3.14 ,recorded") == ["facing", "0.8,-0.5,3.14", "recorded"]
    with pytest.raises(ValueError, match="--placements needs at least one placement"):
        _placements(" , ")


def test_health_refuses_a_name_that_is_no_service_and_a_timeout_not_above_zero(
        capsys: pytest.CaptureFixture[str]) -> None:
    err = refused(capsys, "health", "safety", "bogus", "--insecure")
    assert err == ("safemimic health: SERVICE 'bogus': not a service; the services are "
                   "perception, safety, executor, config_api")
    for timeout in ("-1", "0"):
        err = refused(capsys, "health", "config-api", "--timeout", timeout, "--insecure")
        assert err == f"safemimic health: --timeout must be > 0 seconds, got {timeout}"
    assert capsys.readouterr().out == ""  # no bus opened: no JSON line


@pytest.mark.parametrize("command", ["variants", "compare", "evaluate"])
def test_help_is_wrapped_keeps_its_examples_and_names_the_arguments_as_the_usage_does(
        command: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COLUMNS", "100")
    with pytest.raises(SystemExit) as exit_:
        safemimic([command, "--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    assert max(len(line) for line in text.splitlines()) <= 100
    assert "``" not in text
    if command != "evaluate":
        assert "\n  safemimic evaluate --suite " in text  # an example as written, on a line of its own
    if command == "variants":
        assert "SOURCE OUT\n" in text and "\n  SOURCE " in text and "\n  OUT " in text


def test_certs_without_an_action_names_the_actions(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        safemimic(["certs"])
    assert exit_.value.code == 2
    assert "the following arguments are required: {init,issue,stack}" in capsys.readouterr().err


def test_config_prints_what_a_service_would_run_with(capsys: pytest.CaptureFixture[str],
                                                      monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """``safemimic config``: the file, the variables and the flags merged as a service merges them,
    one value by its dotted name, the token hidden; a bad value or name refused (exit 2)."""
    site = tmp_path / "site.yaml"
    site.write_text("safety:\n  gain: 12.0\napi:\n  token: " + "s" * 32 + "\n")
    monkeypatch.setenv("SAFEMIMIC__SAFETY__GAMMA", "5")
    assert safemimic(["config", "--config", str(site), "--connect", "tcp/10.0.0.2:7447"]) == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["safety"]["gain"] == 12.0 and printed["safety"]["gamma"] == 5.0
    assert printed["bus"]["connect"] == ["tcp/10.0.0.2:7447"]
    assert printed["api"]["token"] == "<set, hidden>"
    assert printed == {**load_config(site, overrides={"bus": {"connect": ["tcp/10.0.0.2:7447"]}}).model_dump(mode="json"),
                       "api": printed["api"]}
    assert safemimic(["config", "--config", str(site), "safety.gain"]) == 0
    assert capsys.readouterr().out == "12.0\n"
    assert safemimic(["config", "--config", str(site), "--json", "safety.u_max"]) == 0
    assert json.loads(capsys.readouterr().out) == load_config(site).safety.u_max
    assert "safety has no 'gian'" in refused(capsys, "config", "safety.gian")
    monkeypatch.setenv("SAFEMIMIC__SAFETY__GAMMA", "-1")
    assert safemimic(["config"]) == 2
    err = capsys.readouterr().err
    assert "safemimic config: invalid configuration:" in err and "safety.gamma (from $SAFEMIMIC__SAFETY__GAMMA)" in err
