"""Temporary files of outputs and checkpoints: created exclusively, never written through a planted link, and never
shared by two writers of one target."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
import torch

from service.cli.parser import main
from symgs_core.codec import ArchiveContents, encode_archive
from symgs_core.files import create_exclusive, whole_file
from symgs_core.pipeline.checkpoint import Checkpoint, load_checkpoint, save_checkpoint
from symgs_core.pipeline.state import LevelState
from symgs_core.synthetic import synthetic_scene

VICTIM = b"precious"


@pytest.fixture(scope="module")
def archive(tmp_path_factory: pytest.TempPathFactory) -> Path:
    scene = synthetic_scene("global", n=64, seed=1, sh_degree=1).scene
    path = tmp_path_factory.mktemp("archive") / "scene.symgs"
    path.write_bytes(encode_archive(ArchiveContents(scene, [], torch.zeros(len(scene), 0, dtype=torch.bool))))
    return path


def _plant(folder: Path, name: str) -> Path:
    """A link named ``name`` in ``folder`` to a victim file elsewhere; returns the victim."""
    victim = folder.parent / f"victim-{name}"
    victim.write_bytes(VICTIM)
    (folder / name).symlink_to(victim)
    return victim


def test_an_exclusive_file_is_never_created_through_a_link(tmp_path: Path) -> None:
    victim = _plant(tmp_path, "link")
    with pytest.raises(FileExistsError):
        create_exclusive(tmp_path / "link")
    assert victim.read_bytes() == VICTIM


def test_decompress_writes_through_no_link_planted_at_a_temporary_name(archive: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    victims = [_plant(out, ".scene.ply.partial")]
    assert main(["decompress", str(archive), "-o", str(out / "scene.ply")]) == 0
    sog = out / "sog"
    sog.mkdir()
    victims += [_plant(sog, f".{name}.partial") for name in ("meta.json", "means_l.webp", "means_u.webp")]
    assert main(["decompress", str(archive), "-o", str(sog / "meta.json")]) == 0
    assert [victim.read_bytes() for victim in victims] == [VICTIM] * len(victims)
    assert (out / "scene.ply").read_bytes().startswith(b"ply\n")
    assert (sog / "meta.json").is_file() and not (sog / "meta.json").is_symlink()


def test_whole_file_leaves_nothing_when_the_write_fails(tmp_path: Path) -> None:
    target = tmp_path / "result.bin"
    with pytest.raises(RuntimeError), whole_file(target) as out:
        out.write(b"half")
        raise RuntimeError("disk full")
    assert list(tmp_path.iterdir()) == []


def test_two_runs_saving_one_checkpoint_at_once_never_fail(tmp_path: Path) -> None:
    """Two runs of one job overlap when a worker's lease lapses during a Redis restart: each saves the job's
    checkpoint while the other does, which with one shared temporary name failed one of them (internal_error)."""
    scene = synthetic_scene("global", n=2000, seed=2, sh_degree=1).scene
    state = LevelState.plain(scene)
    path = tmp_path / "checkpoints" / "levels.pt"
    errors: list[BaseException] = []

    def save(times: int) -> None:
        try:
            for _ in range(times):
                save_checkpoint(Checkpoint(path, "job"), state, [], False, 123)
        except BaseException as exc:  # noqa: BLE001 - reported by the assertion below
            errors.append(exc)

    runs = [threading.Thread(target=save, args=(40,)) for _ in range(2)]
    for run in runs:
        run.start()
    for run in runs:
        run.join()
    assert errors == []
    assert load_checkpoint(Checkpoint(path, "job"), torch.device("cpu")) is not None
    assert [p.name for p in path.parent.iterdir()] == ["levels.pt"]
