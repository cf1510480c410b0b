"""`symgs submit` and `symgs fetch` against a scripted API: each scene's results in a folder of its own, a 503 ridden
out, and local mistakes (a dataset folder that is not one, downloads that cannot be written) as one line and exit 2."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from service.cli import main
from tests.unit._scripted_api import ScriptedApi, events, job, serving, unavailable

A, B = "a" * 32, "b" * 32
NOWHERE = "http://127.0.0.1:9"  # for commands refused before they ask the API anything


def _scene(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"ply\n")  # the scripted API does not read it
    return path


def _one_error_line(capsys: pytest.CaptureFixture[str], command: str) -> str:
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith(f"symgs {command}: error: "), err
    return err


def _finished(job_id: str, result: bytes) -> dict:
    return {
        f"GET /v1/jobs/{job_id}/events": [events(("1", "succeeded"))],
        f"GET /v1/jobs/{job_id}": [job(job_id, "succeeded", ("result.symgs",))],
        f"GET /v1/jobs/{job_id}/result": [(200, {}, result)],
    }


def test_scenes_sharing_a_name_download_into_folders_of_their_own(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    first, second = _scene(tmp_path / "a" / "scene.ply"), _scene(tmp_path / "b" / "scene.ply")
    api = ScriptedApi({
        "POST /v1/jobs": [job(A, "queued"), job(B, "queued")],
        **_finished(A, b"first"), **_finished(B, b"second"),
        # the API's Redis restarts while the first job is followed: the command waits, as Retry-After asks
        f"GET /v1/jobs/{A}/events": [unavailable("0"), events(("1", "succeeded"))],
    })  # fmt: skip
    out = tmp_path / "out"
    with serving(api) as url:
        assert main(["submit", str(first), str(second), "-o", str(out), "--server", url]) == 0, capsys.readouterr()
    written = {p.relative_to(out).as_posix(): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert written == {"a/scene/result.symgs": b"first", "b/scene/result.symgs": b"second"}
    assert len(api.asked(f"GET /v1/jobs/{A}/events")) == 2
    assert "a/scene.ply" in capsys.readouterr().out  # the bars and the table say which is which


def test_a_lone_scene_keeps_its_folder_name(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    scene = _scene(tmp_path / "deep" / "chair.ply")
    api = ScriptedApi({"POST /v1/jobs": [job(A, "queued")], **_finished(A, b"chair")})
    with serving(api) as url:
        assert main(["submit", str(scene), "-o", str(tmp_path / "out"), "--server", url]) == 0, capsys.readouterr()
    assert (tmp_path / "out" / "chair" / "result.symgs").read_bytes() == b"chair"


@pytest.mark.parametrize(
    "names", [("x/scene.ply", "x/scene.ply"), ("x/scene.ply", "x/scene.PLY"), ("x.ply", "x/s.ply", "y/s.ply")]
)
def test_scenes_whose_results_would_mix_are_refused_before_any_upload(tmp_path: Path, capsys, names) -> None:  # noqa: ANN001
    scenes = [str(_scene(tmp_path / name)) for name in names]
    assert main(["submit", *scenes, "-o", str(tmp_path / "out"), "--server", NOWHERE]) == 2
    assert "would mix their results" in _one_error_line(capsys, "submit")
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("images", ["missing", "scene.ply"])
def test_images_that_are_not_a_folder_give_one_line(tmp_path: Path, capsys, images: str) -> None:  # noqa: ANN001
    scene = _scene(tmp_path / "scene.ply")
    assert main(["submit", str(scene), "--images", str(tmp_path / images), "--server", NOWHERE]) == 2
    assert f"--images {tmp_path / images} is not a folder" in _one_error_line(capsys, "submit")


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full, a device whose every write fails")
def test_downloads_that_cannot_be_written_give_one_line(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "out"
    out.mkdir()
    (out / "result.symgs").symlink_to("/dev/full")  # a full disk
    api = ScriptedApi(_finished(A, b"x" * 4096))
    with serving(api) as url:
        assert main(["fetch", A, "-o", str(out), "--server", url]) == 2
    assert "cannot write" in (err := _one_error_line(capsys, "fetch")) and "No space left on device" in err, err


def test_fetch_rides_out_a_503_and_writes_each_file_whole(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """A download answered 503 (Redis restarting) or cut short is tried again; nothing is left under the result's
    name but the whole file."""
    script = _finished(A, b"x" * 4096)
    script[f"GET /v1/jobs/{A}/result"] = [unavailable("0"), unavailable("0"), (200, {}, b"x" * 4096)]
    api = ScriptedApi(script)
    out = tmp_path / "out"
    with serving(api) as url:
        assert main(["fetch", A, "-o", str(out), "--server", url]) == 0, capsys.readouterr().err
    assert (out / "result.symgs").read_bytes() == b"x" * 4096
    assert len(api.asked(f"GET /v1/jobs/{A}/result")) == 3
    assert sorted(p.name for p in out.iterdir()) == ["result.symgs"]  # no partial file left


def test_submissions_carry_one_idempotency_key_across_retries(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    scene = _scene(tmp_path / "s.ply")
    api = ScriptedApi({"POST /v1/jobs": [unavailable("0"), job(A, "queued")], **_finished(A, b"r")})
    with serving(api) as url:
        assert main(["submit", str(scene), "--server", url, "--no-wait"]) == 0, capsys.readouterr().err
    keys = [headers.get("idempotency-key") for headers in api.asked("POST /v1/jobs")]
    assert len(keys) == 2 and keys[0] and keys[0] == keys[1]


@pytest.mark.parametrize("hostile", ["../../escape.bin", "/abs/escape.bin", "charts/..\\..\\x.png", "a/\x1b[2Jb.png"])
def test_fetch_refuses_result_names_that_leave_the_folder_and_writes_nothing(
    tmp_path: Path, capsys, hostile: str  # noqa: ANN001
) -> None:
    """A server (or anyone in the middle of plain http) listing ``../../x`` or ``/abs/path`` must not make the client
    write there: the fetch stops before any download, in one line, exit 2."""
    out = tmp_path / "deep" / "er" / "out"
    name = str(tmp_path / "abs" / "escape.bin") if hostile.startswith("/") else hostile
    script = _finished(A, b"r")
    script[f"GET /v1/jobs/{A}"] = [job(A, "succeeded", ("result.symgs", name))]
    for path in ("/v1/escape.bin", f"/v1/jobs/{A}/{name}", f"/v1/jobs/{A}/{name.replace(chr(92), '/')}"):
        script[f"GET {path}"] = [(200, {}, b"pwned")]
    api = ScriptedApi(script)
    with serving(api) as url:
        assert main(["fetch", A, "-o", str(out), "--server", url]) == 2
        assert "outside" in _one_error_line(capsys, "fetch")
        submitted = _scene(tmp_path / "s.ply")
        script["POST /v1/jobs"] = [job(A, "queued")]
        assert main(["submit", str(submitted), "-o", str(out), "--server", url]) == 2
        assert "outside" in capsys.readouterr().err
    written = [p for p in tmp_path.rglob("*") if p.is_file() and p.name != "s.ply"]
    assert written == [], written
    assert not api.asked(f"GET /v1/jobs/{A}/result")
