"""`symgs compress`, `decompress` and `evaluate` on files: results that decode, and clean errors."""

from __future__ import annotations

import json
import os
import re
import subprocess
import time

import pytest

from service.cli import main
from symgs_core.bench.photos import photographed
from symgs_core.export import save_scene
from symgs_core.export.formats import EXPORTS
from symgs_core.ply import load_scene
from symgs_core.synthetic import synthetic_scene

FAST = ["--iterations", "5", "--resolution", "48", "--eval-resolution", "48", "--train-views", "4", "--fit-views", "2",
        "--eval-views", "2"]
LINE = re.compile(r"^compress: (\w+)(?: L\d+)? +(\d+)%  elapsed \d+:\d\d  left (?:\d+:\d\d|-:--)  ")


@pytest.fixture(scope="module")
def scene_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "chair.ply"
    save_scene(synthetic_scene("global", n=1200, seed=2).scene, path)
    return path


def test_compress_decompress_evaluate(scene_file, tmp_path, capsys):
    # a report's missing folder is made, as the archive's is
    archive, report, decoded = tmp_path / "a.symgs", tmp_path / "reports" / "r.json", tmp_path / "d.ply"
    assert (
        main(["compress", str(scene_file), "-o", str(archive), "--report", str(report), "--max-levels", "1", *FAST])
        == 0
    )
    # stderr is not a terminal here: plain progress lines, one per stage at least, ending at 100%
    lines = capsys.readouterr().err.splitlines()
    progress = [LINE.match(line) for line in lines]
    assert lines and all(progress), lines
    stages = [m.group(1) for m in progress]
    assert stages[0] == "load" and {"views", "encode", "evaluate"} <= set(stages)
    assert int(progress[-1].group(2)) == 100
    assert [int(m.group(2)) for m in progress] == sorted(int(m.group(2)) for m in progress)
    figures = json.loads(report.read_text())
    assert figures["output_bytes"] == archive.stat().st_size
    assert main(["decompress", str(archive), "-o", str(decoded)]) == 0
    assert len(load_scene(decoded)) == figures["gaussians"]["decoded"]
    capsys.readouterr()
    assert main(["evaluate", str(scene_file), str(archive), "--views", "2", "--resolution", "48", "--json"]) == 0
    from_archive = json.loads(capsys.readouterr().out)
    assert main(["evaluate", str(scene_file), str(decoded), "--views", "2", "--resolution", "48", "--json"]) == 0
    from_ply = json.loads(capsys.readouterr().out)
    assert from_archive["gaussians"] == from_ply["gaussians"] == figures["gaussians"]["decoded"]
    assert from_archive["psnr"] == pytest.approx(from_ply["psnr"], abs=1e-6)  # the .ply is the archive, decoded
    assert from_archive["psnr"] is None or from_archive["psnr"] > 30.0


def test_bad_inputs_exit_2_with_a_message(scene_file, tmp_path, capsys):
    corrupt = tmp_path / "corrupt.symgs"
    corrupt.write_bytes(b"\x89SYMGS\r\n" + b"\x00" * 40)
    assert main(["decompress", str(corrupt), "-o", str(tmp_path / "x.ply")]) == 2
    assert main(["evaluate", str(scene_file), str(corrupt)]) == 2
    assert main(["compress", str(tmp_path / "missing.ply"), "-o", str(tmp_path / "m.symgs")]) == 2
    not_ply = tmp_path / "not.ply"
    not_ply.write_text("hello")
    assert main(["compress", str(not_ply), "-o", str(tmp_path / "n.symgs"), *FAST, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "error" in err and "Traceback" not in err
    photographed("local", tmp_path / "shots", n=300, photos=4, tests=1, resolution=24)
    elsewhere = ["compress", str(scene_file), "--images", str(tmp_path / "shots"), "-o", str(tmp_path / "e.symgs")]
    assert main([*elsewhere, *FAST, "--quiet"]) == 2
    assert "symgs compress: error: images_mismatch: " in capsys.readouterr().err  # the code a service client sees


def test_errors_name_the_code_the_api_would(scene_file, tmp_path, capsys):  # noqa: ANN001
    from symgs_core.scene import GaussianScene

    empty = tmp_path / "empty.ply"
    save_scene(GaussianScene.empty(0), empty)
    cut = tmp_path / "cut.ply"
    cut.write_bytes(scene_file.read_bytes()[:-100])
    corrupt = tmp_path / "corrupt.symgs"
    corrupt.write_bytes(b"\x89SYMGS\r\n" + b"\x00" * 40)  # a format version no build wrote
    for argv, error in [
        (["evaluate", str(cut), str(scene_file)], "symgs evaluate: error: truncated: "),
        (["evaluate", str(scene_file), str(cut)], "symgs evaluate: error: truncated: "),
        (["evaluate", str(scene_file), str(corrupt)], "symgs evaluate: error: unsupported_version: "),
        (["evaluate", str(empty), str(scene_file)], "symgs evaluate: error: empty_scene: "),
        (["compress", str(empty), "-o", str(tmp_path / "e.symgs"), "--quiet"], "symgs compress: error: empty_scene: "),
        (["decompress", str(corrupt), "-o", str(tmp_path / "x.ply")], f"symgs decompress: error: {corrupt}: "
         "unsupported_version: "),
    ]:  # fmt: skip
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert err.startswith(error) and err.count("unsupported_version") <= 1, err  # the code once, not twice


def _bad_archives(scene_file) -> dict[str, bytes]:  # noqa: ANN001
    from symgs_core.codec import encode_archive
    from tests.unit.test_archive import random_contents
    from tests.unit.test_archive_hostile import reframe, split

    good = encode_archive(random_contents(30, 1, 1, seed=4, special=False), codec="quantized")
    header, body = split(good)
    header["sections"][0]["params"]["step"] = 1e300  # decoded positions would be infinite
    return {"truncated": good[:-9], "empty": b"", "a PLY": scene_file.read_bytes()[:4096],
            "absurd position step": reframe(header, body)}  # fmt: skip


@pytest.mark.parametrize("extension", [fmt.extension for fmt in EXPORTS])
def test_bad_archives_give_one_line_and_exit_2_for_every_format(scene_file, tmp_path, capsys, extension):  # noqa: ANN001
    for name, data in _bad_archives(scene_file).items():
        archive, output = tmp_path / "bad.symgs", tmp_path / f"out{extension}"
        archive.write_bytes(data)
        assert main(["decompress", str(archive), "-o", str(output)]) == 2, name
        captured = capsys.readouterr()
        assert captured.out == "" and len(captured.err.strip().splitlines()) == 1, (name, captured.err)
        assert captured.err.startswith("symgs decompress: error: ") and not output.exists(), name


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["compress", "SCENE", "-o", "adir"], "-o adir is a folder; a file is expected there"),
        (["compress", "SCENE", "-o", "afile/x.symgs"], "-o afile/x.symgs: afile is a file, not a folder"),
        (["compress", "SCENE", "-o", "afile/deeper/x.symgs"], "afile is a file, not a folder"),
        (["compress", "SCENE", "-o", "x.symgs", "--report", "adir"], "--report adir is a folder"),
        (["compress", "SCENE", "-o", "x.symgs", "--report", "afile/r.json"], "--report afile/r.json: afile is a file"),
        (["compress", "SCENE", "-o", "x.symgs", "--pictures", "afile"], "--pictures afile is a file; a folder is"),
        (["compress", "SCENE", "-o", "x.symgs", "--pictures", "afile/p"], "--pictures afile/p: afile is a file"),
        (["decompress", "ARCHIVE", "-o", "adir.ply"], "-o adir.ply is a folder"),
        (["compress", "SCENE", "-o", "SCENE"], "is the same file as the scene"),
        (["compress", "SCENE", "-o", "x.symgs", "--report", "adir/../x.symgs"],
         "--report adir/../x.symgs is the same file as -o x.symgs"),
        (["decompress", "ARCHIVE", "-o", "afile/x.spz"], "-o afile/x.spz: afile is a file, not a folder"),
        (["bench", "SCENE", "--out", "afile"], "--out afile is a file; a folder is expected there"),
        (["fetch", "some-job", "-o", "afile/results"], "-o afile/results: afile is a file"),
        (["submit", "SCENE", "-o", "afile"], "-o afile is a file"),
        (["demo", "-o", "afile"], "-o afile is a file"),
    ],
)
def test_unwritable_outputs_exit_2_before_any_work(scene_file, tmp_path, capsys, monkeypatch, argv, message):  # noqa: ANN001
    (tmp_path / "adir").mkdir()
    (tmp_path / "adir.ply").mkdir()
    (tmp_path / "afile").write_text("")
    archive = tmp_path / "a.symgs"
    archive.write_bytes(b"not read: the output is checked first")
    monkeypatch.chdir(tmp_path)
    before = sorted(tmp_path.rglob("*"))
    argv = [str(scene_file) if a == "SCENE" else str(archive) if a == "ARCHIVE" else a for a in argv]
    assert main([*argv, *(FAST if argv[0] == "compress" else [])]) == 2
    captured = capsys.readouterr()
    # one line and no progress lines: the pipeline never started
    assert captured.out == "" and len(captured.err.splitlines()) == 1, captured.err
    assert captured.err.startswith(f"symgs {argv[0]}: error: ") and message in captured.err, captured.err
    assert sorted(tmp_path.rglob("*")) == before


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full, a device whose every write fails")
def test_a_write_that_fails_after_the_work_exits_2_in_one_line(scene_file, tmp_path, capsys):  # noqa: ANN001
    """A disk that fills during the work: one line naming the file, exit 2, no traceback."""
    full = tmp_path / "full.ply"
    full.symlink_to("/dev/full")
    archive = tmp_path / "a.symgs"
    for argv in (["compress", str(scene_file), "-o", "/dev/full", *FAST, "--quiet"],
                 ["compress", str(scene_file), "-o", str(archive), "--report", "/dev/full", *FAST, "--quiet"],
                 ["decompress", str(archive), "-o", str(full)]):  # fmt: skip
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert len(err.splitlines()) == 1 and "cannot write" in err and "No space left" in err, err
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no partial file left


def test_an_output_in_a_folder_one_cannot_write_exits_2(scene_file, tmp_path, capsys, monkeypatch):  # noqa: ANN001
    monkeypatch.setattr("service.cli.parser.os.access", lambda path, mode: False)  # tests may run as root
    assert main(["compress", str(scene_file), "-o", str(tmp_path / "new" / "x.symgs"), *FAST]) == 2
    assert f"{tmp_path} is not writable" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--views", "0"], "--views must be in 1..256, got 0"),
        (["--views", "-3"], "--views must be in 1..256, got -3"),
        (["--resolution", "100000"], "--resolution must be in 16..2048, got 100000"),
        (["--resolution", "8"], "--resolution must be in 16..2048, got 8"),
        (["--seed", "99999999999999999999999"], "--seed must be in 0..2147483647, got 99999999999999999999999"),
        (["--seed", "-1"], "--seed must be in 0..2147483647, got -1"),
    ],
)
def test_evaluate_settings_out_of_range_exit_2(scene_file, capsys, extra, message):  # noqa: ANN001
    assert main(["evaluate", str(scene_file), str(scene_file), *extra]) == 2
    err = capsys.readouterr().err
    assert err == f"symgs evaluate: error: {message}\n", err


@pytest.mark.parametrize("seed", ["99999999999999999999999", "-1", str(2**31)])
def test_compress_seed_out_of_range_exits_2(scene_file, tmp_path, capsys, seed):  # noqa: ANN001
    output = tmp_path / "x.symgs"
    assert main(["compress", str(scene_file), "-o", str(output), "--seed", seed, *FAST]) == 2
    assert capsys.readouterr().err == f"symgs compress: error: --seed must be in 0..2147483647, got {seed}\n"
    assert not output.exists()


def test_the_command_exits_2_without_a_traceback_on_an_output_folder(scene_file, tmp_path):  # noqa: ANN001
    from service.cli.stack import SYMGS

    start = time.monotonic()
    done = subprocess.run([*SYMGS, "compress", str(scene_file), "-o", str(tmp_path)], capture_output=True, text=True)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr
    assert done.stderr == f"symgs compress: error: -o {tmp_path} is a folder; a file is expected there\n"
    assert time.monotonic() - start < 30  # the compression (minutes at the default preset) never ran


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["info", "adir"], "scene file adir is a folder, not a file"),
        (["detect", "adir"], "scene file adir is a folder, not a file"),
        (["compress", "adir", "-o", "x.symgs"], "scene file adir is a folder, not a file"),
        (["compress", "SCENE", "-o", "x.symgs", "--images", "SCENE"], "is a file, not a folder"),
        (["decompress", "adir", "-o", "x.ply"], "archive adir is a folder, not a file"),
        (["evaluate", "SCENE", "adir"], "candidate adir is a folder, not a file"),
        (["evaluate", "nowhere.ply", "SCENE"], "reference nowhere.ply does not exist"),
    ],
)
def test_an_input_of_the_wrong_kind_is_named(scene_file, tmp_path, capsys, monkeypatch, argv, message):  # noqa: ANN001
    (tmp_path / "adir").mkdir()
    monkeypatch.chdir(tmp_path)
    assert main([str(scene_file) if a == "SCENE" else a for a in argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"symgs {argv[0]}: error: ") and message in err and len(err.splitlines()) == 1, err


def test_a_mirror_that_does_not_pay_without_photographs_comes_with_a_note(tmp_path, capsys):  # noqa: ANN001
    """Halves that are two reconstructions of one object: against the upload's own renders no level pays, and the
    command says what would let one (the report carries the same note)."""
    scene = tmp_path / "capture.ply"
    save_scene(synthetic_scene("global", n=1500, seed=2, sh_degree=1, capture="independent").scene, scene)
    report = tmp_path / "r.json"
    argv = ["compress", str(scene), "-o", str(tmp_path / "c.symgs"), "--report", str(report), "--max-levels", "1"]
    assert main([*argv, *FAST, "--quiet"]) == 0
    notes = [line for line in capsys.readouterr().out.splitlines() if line.startswith("note: ")]
    figures = json.loads(report.read_text())
    assert figures["levels"] and not any(level["accepted"] for level in figures["levels"])
    assert len(notes) == 1 and "--images" in notes[0] and figures["notes"] == [notes[0].removeprefix("note: ")]
