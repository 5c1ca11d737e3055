"""The CLI end to end: synth, merge, and every bad input as a one-line error with exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from backend.cli import main


@pytest.fixture(scope="module")
def patch_folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("synth")
    code = main(
        [
            "synth",
            "--out",
            str(out),
            "--surface",
            "folded",
            "--rows",
            "2",
            "--cols",
            "3",
            "--patch",
            "0.8e-6",
            "--pixels",
            "40",
            "--overlap",
            "0.4",
            "--seed",
            "3",
        ]
    )
    assert code == 0
    return out


def test_synth_writes_a_patch_set_with_its_truth(patch_folder: Path) -> None:
    manifest = json.loads((patch_folder / "manifest.json").read_text())
    assert manifest["format"] == "mosaic-afm/patchset@1"
    assert len(manifest["patches"]) == 6
    truth = json.loads((patch_folder / "truth.json").read_text())
    assert len(truth["patches"]) == 6
    assert np.load(patch_folder / "truth.npy").ndim == 2


def test_merge_writes_the_result_and_a_summary(
    patch_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["merge", str(patch_folder / "manifest.json"), "--out", str(tmp_path)])
    assert code == 0
    out = capsys.readouterr()
    assert out.out.startswith("merged 6 patches (default)")
    assert "converged" in out.out
    for name in ("mosaic.npy", "mosaic.json", "preview.png"):
        assert (tmp_path / name).is_file()


def test_merge_self_calibrates_when_asked(
    patch_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    args = ["merge", str(patch_folder / "manifest.json"), "--out", str(tmp_path)]
    assert main([*args, "--self-calibrate", "--quiet"]) == 0
    assert "scanner bend: none stood out of the noise" in capsys.readouterr().out
    doc = json.loads((tmp_path / "mosaic.json").read_text())
    assert doc["parameters"]["self_calibrate"] is True
    assert doc["scan_distortion"]["significant"] == [False, False]


@pytest.mark.parametrize(
    "args",
    [
        ["merge", "/no/such/manifest.json", "--out", "{tmp}"],
        ["merge", "{patches}/manifest.json", "--out", "{tmp}", "--cell", "-1"],
        ["merge", "{patches}/manifest.json", "--out", "{tmp}", "--max-iter", "0"],
        ["merge", "{patches}/manifest.json", "--out", "{tmp}", "--coarse-cell", "0"],
        [
            "merge",
            "{patches}/manifest.json",
            "--out",
            "{tmp}",
            "--method",
            "paper",
            "--self-calibrate",
        ],
        ["synth", "--out", "{tmp}", "--rows", "1", "--cols", "1"],
        ["synth", "--out", "{tmp}", "--overlap", "1.5"],
        ["synth", "--out", "{tmp}", "--surface", "image"],
        ["synth", "--out", "{tmp}", "--pixels", "4,x"],
    ],
)
def test_bad_input_is_a_message_and_exit_2(
    args: list[str], patch_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = [a.format(tmp=tmp_path / "o", patches=patch_folder) for a in args]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "error:" in err and "Traceback" not in err


def test_a_broken_patch_file_is_named(
    patch_folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "set"
    bad.mkdir()
    for f in patch_folder.iterdir():
        (bad / f.name).write_bytes(f.read_bytes())
    (bad / "p002.npy").write_bytes(b"garbage")
    assert main(["merge", str(bad / "manifest.json"), "--out", str(tmp_path / "o")]) == 2
    assert "patch 'p002'" in capsys.readouterr().err


@pytest.mark.parametrize(
    "args",
    [
        ["sim-mcs", "--channels", "0"],
        ["sim-mcs", "--speed", "fast"],
        ["sim-mcs", "--speed", "-1"],
        ["sim-mcs", "--port", "70000"],
    ],
)
def test_sim_mcs_bad_options(args: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(args) == 2
    assert "error:" in capsys.readouterr().err


def test_sim_mcs_serves_the_protocol() -> None:
    import subprocess
    import sys

    from hardware.smaract_mcs import MCSController

    proc = subprocess.Popen(
        [sys.executable, "-m", "backend.cli", "sim-mcs", "--channels", "2"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        url = line.split(" at ")[1].strip()
        with MCSController.open(url, timeout=2.0) as c:
            assert c.channel_count() == 2
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_sim_scan_writes_a_patch_set_that_merges(tmp_path: Path) -> None:
    out = tmp_path / "scan"
    assert (
        main(
            [
                "sim-scan",
                "--out",
                str(out),
                "--rows",
                "1",
                "--cols",
                "2",
                "--surface",
                "folded",
                "--patch",
                "0.6e-6",
                "--pixels",
                "24",
                "--overlap",
                "0.5,0",
            ]
        )
        == 0
    )
    manifest = json.loads((out / "manifest.json").read_text())
    assert [p["id"] for p in manifest["patches"]] == ["p000", "p001"]
    assert main(["merge", str(out / "manifest.json"), "--out", str(tmp_path / "m"), "--quiet"]) == 0
    doc = json.loads((tmp_path / "m" / "mosaic.json").read_text())
    assert all(p["correspondences"] > 0 for p in doc["patches"])


@pytest.mark.parametrize(
    "args",
    [["--patch", "2e-6"], ["--line-rate", "0"], ["--rows", "0"], ["--overlap", "1"]],
)
def test_sim_scan_bad_options(
    args: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["sim-scan", "--out", str(tmp_path / "x"), *args]) == 2
    assert "error:" in capsys.readouterr().err


def test_the_progress_bar_tells_the_stage_and_the_time_to_go() -> None:
    import io

    from backend.cli.common import ProgressBar, duration
    from merge import Status

    stream = io.StringIO()
    bar = ProgressBar(stream=stream, every=3600.0)
    bar.status(Status("start", "correlating the overlaps", 0.1, 10.0))
    bar.status(Status("start", "correlating the overlaps", 0.2, 20.0))  # same stage, too soon
    bar(3, 1.5e-9)
    bar.status(Status("refine", "refining, level 2 of 2", 0.5, 50.0))
    lines = stream.getvalue().splitlines()
    assert lines == [
        "merge: correlating the overlaps:  10 %, 1 min 30 s to go",
        "merge: refining, level 2 of 2:  50 %, 50 s to go, residual 1.500 nm",
    ]
    assert duration(3725) == "1 h 02 min"


def test_users_add_reads_the_password_from_stdin_and_list_shows_no_secret(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import io

    data = str(tmp_path / "data")
    monkeypatch.setattr("sys.stdin", io.StringIO("a long password\n"))
    assert main(["users", "--data-dir", data, "add", "ada", "--role", "operator"]) == 0
    monkeypatch.setattr("sys.stdin", io.StringIO("short\n"))
    assert main(["users", "--data-dir", data, "add", "bob", "--role", "admin"]) == 2
    assert "at least 8 characters" in capsys.readouterr().err
    monkeypatch.setattr("sys.stdin", io.StringIO("another password\n"))
    assert main(["users", "--data-dir", data, "add", "ada", "--role", "admin"]) == 2
    assert "already a user 'ada'" in capsys.readouterr().err
    assert main(["users", "--data-dir", data, "role", "ada", "admin"]) == 0
    assert main(["users", "--data-dir", data, "disable", "ada"]) == 0
    capsys.readouterr()
    assert main(["users", "--data-dir", data, "list"]) == 0
    listed = capsys.readouterr().out
    assert "ada" in listed and "admin" in listed and "disabled" in listed
    assert "a long password" not in listed and "argon2" not in listed
    assert main(["users", "--data-dir", data, "enable", "nobody"]) == 2


def test_serve_in_the_users_mode_without_users_says_how_to_add_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("MOSAIC_AUTH", "users")
    assert main(["serve", "--data-dir", str(tmp_path), "--port", "1"]) == 2
    assert "mosaic-afm users add NAME --role admin" in capsys.readouterr().err
