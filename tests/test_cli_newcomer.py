"""A newcomer's first hour: --list-keys alone, prepare's exit status, the QA column, plain help text."""

from __future__ import annotations

from pathlib import Path

import pytest

from assets_store.manifest import Fingerprint, Manifest
from assets_store.store import Store
from ops.cli import main
from ops.config.presets import preset
from ops.engine.config_tree import describe_keys
from ops.pipeline.photo_run import PhotoOutcome, StageOutcome
from ops.reporting.run_table import format_run_table, qa_verdict
from orchestration.cli import main as dagster_main

OPS_COMMANDS = ([], ["doctor"], ["prepare"], ["run"], ["report"])
DAGSTER_COMMANDS = ([], ["add-photos"], ["materialize"], ["status"], ["gpu-pool"], ["migrate-history"])


def test_list_keys_needs_no_photo_or_out(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "--list-keys"]) == 0
    lines = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()}
    assert len(lines) == len(describe_keys(preset("draft"))) and "nerf.loop.steps" in lines
    assert not [line for line in lines.values() if "``" in line]  # plain text, not reStructuredText
    assert "Alias MORPHEUS_HASHGRID" in lines["execution.hashgrid"]
    # --preset and --set still apply to what it lists.
    assert main(["run", "--list-keys", "--preset", "paper", "--set", "nerf.loop.steps=7"]) == 0
    lines = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()}
    assert lines["nerf.loop.steps"].split()[1] == "7"


def test_run_without_a_photo_or_out_names_what_is_missing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run"]) == 2
    err = capsys.readouterr().err
    assert "give a photo or folder and --out" in err and "--list-keys needs neither" in err
    assert main(["run", "examples/photos/mug.jpg"]) == 2
    assert "give --out" in capsys.readouterr().err
    assert main(["run", "--out", str(tmp_path)]) == 2
    assert "give a photo or folder (usage" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())  # nothing written on a usage error


def test_prepare_fails_on_a_bad_photo_unless_failures_are_allowed(tmp_path: Path,
                                                                   capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "broken.jpg"
    bad.write_text("this is not a photo")
    assert main(["prepare", str(bad), "--out", str(tmp_path / "ref")]) == 1
    captured = capsys.readouterr()
    assert "failed" in captured.out and "morpheus3d prepare: 1 of 1 photo(s) failed: broken.jpg" in captured.err
    assert main(["prepare", str(bad), "--out", str(tmp_path / "ref"), "--allow-failures"]) == 0
    assert "broken.jpg" in capsys.readouterr().err  # still named, only the exit status differs
    assert main(["prepare", str(bad), "--out", str(tmp_path / "ref"), "--strict"]) == 1  # the default, accepted
    with pytest.raises(SystemExit) as exc:  # contradictory flags are a usage error
        main(["prepare", str(bad), "--out", str(tmp_path / "ref"), "--strict", "--allow-failures"])
    assert exc.value.code == 2


def _outcome(name: str, qa: dict | None, error: str | None = None) -> PhotoOutcome:
    fp = Fingerprint({}, "h", "v")
    stages = [StageOutcome("bake", "ran", 1.0, Manifest("bake", name, fp, metrics={"ref_psnr": 21.04}))]
    if qa is not None:
        stages.append(StageOutcome("qa", "ran", 1.0, Manifest("qa", name, fp, metrics=qa)))
    return PhotoOutcome(Path(name), name, stages, error)


def test_run_table_has_a_qa_verdict_column(tmp_path: Path) -> None:
    outcomes = [_outcome("a.jpg", {"verdict": "pass", "failed_checks": 0}),
                _outcome("b.jpg", {"verdict": "warn", "failed_checks": 1}),
                _outcome("c.jpg", {"verdict": "fail", "failed_checks": 3}),
                _outcome("d.jpg", None)]  # --until bake: no QA stage
    assert [qa_verdict(o) for o in outcomes] == ["pass", "warn (1 check)", "fail (3 checks)", "-"]
    lines = format_run_table(outcomes, Store(tmp_path)).splitlines()
    header = lines[0].split()
    assert header[:4] == ["PHOTO", "KEY", "OUTCOME", "QA"]
    column = lines[0].index("QA")
    assert [line[column:].split("  ")[0] for line in lines[1:5]] == ["pass", "warn (1 check)", "fail (3 checks)",
                                                                       "-"]
    assert "21.0 dB" in lines[1] and "qa/qa.json" in lines[-1]


def _help(run: object, argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as exc:
        run([*argv, "--help"])  # type: ignore[operator]
    assert exc.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("run,commands", [(main, OPS_COMMANDS), (dagster_main, DAGSTER_COMMANDS)])
def test_help_text_is_plain(run: object, commands: tuple[list[str], ...], capsys: pytest.CaptureFixture[str]) -> None:
    top = _help(run, [], capsys)
    for argv in commands:
        text = _help(run, argv, capsys)
        assert argv == [] or argv[0] in top  # every subcommand is checked
        assert "``" not in text and "`" not in text, f"{argv}: markup in the help text:\n{text}"
    if run is dagster_main:
        assert "Register photos as partitions" in top and "$DAGSTER_HOME" in top
