"""Stability where the method fails: scenes whose mirrors are rough, partial, ambiguous, too small or absent.

Whatever the scene, a job ends with an archive that decodes to finite Gaussians, a report that tells what the archive
holds, and never more bytes than the same preset without mirrors.
"""

from __future__ import annotations

import importlib
import math
from dataclasses import replace

import pytest
import torch

from symgs_core.codec import decode_archive, expand_archive, expanded_count
from symgs_core.config import CompressConfig
from symgs_core.mirror import Plane, reflect
from symgs_core.pipeline import CompressResult, compress
from symgs_core.scene import GaussianScene
from symgs_core.sh import C0
from symgs_core.synthetic import synthetic_scene
from symgs_core.views import evaluate, self_supervised_views

CONFIG = CompressConfig.for_preset(
    "balanced", iterations=10, resolution=32, train_views=4, fit_views=2, eval_views=2, eval_resolution=32,
    max_levels=2, device="cpu", pictures=False,
)  # fmt: skip


def _compress_and_check(scene: GaussianScene, config: CompressConfig = CONFIG) -> CompressResult:
    """Compress ``scene`` with and without mirrors and check the result against its archive and against the plain
    codec: decodable to finite values, every figure of the report true of the archive, never larger."""
    result = compress(scene, config=config)
    plain = compress(scene, config=replace(config, use_mirrors=False)).archive
    report, archive = result.report, result.archive

    contents = decode_archive(archive)
    decoded = expand_archive(contents)
    assert len(decoded) == report.gaussians.decoded == expanded_count(contents.bits)
    for name, values in decoded.tensors().items():
        assert torch.isfinite(values).all(), name

    assert report.output_bytes == len(archive) == report.stages[-1].bytes_after
    assert report.ratio_to_baseline == report.baseline_bytes / len(archive)
    assert report.gaussians.input == len(scene) == contents.meta["input_gaussians"]
    assert report.gaussians.stored == len(contents.stored)
    accepted = report.accepted_levels
    assert len(contents.planes) == len(accepted)
    for level, plane in zip(accepted, contents.planes):
        assert all(abs(a - b) < 1e-6 for a, b in zip(level.normal, plane.normal))
        assert abs(level.offset - plane.offset) < 1e-6
    # Each level's record tells why: below the floor (never judged), or judged against the best archive so far.
    best = len(plain)
    for level in report.levels:
        if level.archive_bytes is None:
            assert not level.accepted and level.psnr_after < report.psnr_floor
        elif level.accepted:
            assert level.archive_bytes < best and level.psnr_after >= report.psnr_floor
            best = level.archive_bytes
        else:
            assert level.archive_bytes >= best
    assert best == len(archive)

    if accepted:
        assert len(archive) < len(plain) == report.plain_codec_bytes
    else:  # the plain codec's archive, byte for byte
        assert archive == plain
        assert report.plain_codec_bytes is None
        assert report.gaussians.decoded == report.gaussians.stored

    for figure in (report.fidelity, report.fitting):
        assert all(math.isfinite(v) or v == math.inf for v in (figure.psnr, figure.psnr_object, figure.ssim))
    assert report.fitting.worst >= report.psnr_floor
    views = self_supervised_views(
        scene, train=config.train_views, fit=config.fit_views, eval=config.eval_views, resolution=config.resolution,
        eval_resolution=config.eval_resolution, background=torch.zeros(3), seed=config.seed,
    )  # fmt: skip
    assert evaluate(decoded, views.fit, views.background) == report.fitting
    assert evaluate(decoded, views.eval, views.background) == report.fidelity
    return result


def _angle(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    """Degrees between two plane normals (either sign)."""
    return math.degrees(math.acos(min(1.0, abs(sum(x * y for x, y in zip(a, b))))))


def _surface(points: torch.Tensor, normals: torch.Tensor, spacing: float, rgb: torch.Tensor) -> GaussianScene:
    """Opaque discs on a surface: round (so a turn about their normal changes nothing), flat along ``normals``."""
    n = len(points)
    z = normals[:, 2]
    quats = torch.stack([1.0 + z, -normals[:, 1], normals[:, 0], torch.zeros(n)], dim=1)  # turns e_z onto the normal
    quats[z < -1.0 + 1e-6] = torch.tensor([0.0, 1.0, 0.0, 0.0])
    radii = torch.tensor([0.7 * spacing, 0.7 * spacing, 0.1 * spacing]).expand(n, 3)
    return GaussianScene(
        means=points, quats=torch.nn.functional.normalize(quats, dim=1), scales=radii.log(),
        opacities=torch.full((n,), 2.0), sh_dc=(rgb.clamp(0.02, 0.98) - 0.5) / C0, sh_rest=torch.zeros(n, 0, 3),
    )  # fmt: skip


def test_independently_captured_halves_with_partners_missing():
    """Each half sampled on its own and jittered, the right half with its own colours and sizes, a fifth of it gone:
    most Gaussians have no exact partner."""
    planted = synthetic_scene("global", n=1500, seed=11, capture="independent", noise=0.004)
    scene, right = planted.scene.clone(), planted.right[0]
    gen = torch.Generator().manual_seed(1)
    scene.sh_dc[right] += 0.1 * torch.randn(len(right), 3, generator=gen)
    scene.scales[right] += 0.1 * torch.randn(len(right), 3, generator=gen)
    keep = torch.ones(len(scene), dtype=torch.bool)
    keep[right[torch.randperm(len(right), generator=gen)[: len(right) // 5]]] = False
    report = _compress_and_check(scene.select(keep)).report
    assert report.levels  # the rough mirror is found and tried, kept only if it pays


def test_a_deformed_half():
    """Twins, then one half bent away from the plane and stretched by 8 %: no plane maps one half onto the other."""
    planted = synthetic_scene("global", n=700, seed=12)
    scene, right = planted.scene.clone(), planted.right[0]
    x = scene.means[right, 0]
    scene.means[right, 1] += 0.5 * x * x
    scene.means[right, 2] *= 1.08
    _compress_and_check(scene)


def test_two_equally_dominant_planes():
    """An object symmetric under x = 0 cut at its median height and mirrored there: two perpendicular planes, each
    halving the scene. Either may come first; both are found, one nested in the other."""
    planted = synthetic_scene("global", n=700, seed=13)
    scene = planted.scene
    height = float(scene.means[:, 1].median())
    top = scene.select(scene.means[:, 1] > height)
    report = _compress_and_check(GaussianScene.cat([top, reflect(top, torch.tensor([0.0, 1.0, 0.0]), height)])).report
    accepted = report.accepted_levels
    assert len(accepted) == 2
    assert abs(_angle(accepted[0].normal, accepted[1].normal) - 90.0) < 1.0
    assert {max(range(3), key=lambda i: abs(level.normal[i])) for level in accepted} == {0, 1}


def test_a_cylinder():
    """Continuous symmetry: every plane through the axis is a mirror, none of them pairs the sampled discs."""
    gen = torch.Generator().manual_seed(3)  # this one once left the plane refinement with no matching Gaussian
    n = 700
    theta = 2.0 * math.pi * torch.rand(n, generator=gen)
    z = 2.0 * torch.rand(n, generator=gen) - 1.0
    radial = torch.stack([theta.cos(), theta.sin(), torch.zeros(n)], dim=1)
    rgb = torch.where((torch.sin(8.0 * z) > 0)[:, None], torch.tensor([0.8, 0.3, 0.2]), torch.tensor([0.2, 0.4, 0.8]))
    points = 0.5 * radial + torch.stack([torch.zeros(n), torch.zeros(n), z], dim=1)
    _compress_and_check(_surface(points, radial, math.sqrt(2.0 * math.pi * 0.5 * 2.0 / n), rgb))


def test_a_sphere():
    """Every plane through the centre is a mirror of a uniformly coloured sphere."""
    gen = torch.Generator().manual_seed(15)
    n = 700
    radial = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=1)
    rgb = torch.tensor([0.7, 0.6, 0.3]) + 0.03 * torch.randn(n, 3, generator=gen)
    _compress_and_check(_surface(0.6 * radial, radial, math.sqrt(4.0 * math.pi * 0.36 / n), rgb))


def test_a_plane_that_drifts_during_the_fine_tune(monkeypatch):
    """The detector's plane a degree off the scene's mirror, as on captures whose halves only roughly agree: the
    fine-tune, which trains the newest plane, moves it towards the mirror, and the archive stores where it ended."""
    planted = synthetic_scene("global", n=700, seed=16)
    truth = planted.planes[0].normal
    assert truth == (1.0, 0.0, 0.0)
    package = importlib.import_module("symgs_core.detect")
    detect = package.detect
    turn = math.radians(1.0)
    tilted = Plane((math.cos(turn), math.sin(turn), 0.0), 0.0)

    calls = []

    def off_by_a_degree(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        calls.append(1)
        return [replace(m, plane=tilted) for m in detect(*args, **kwargs)]

    monkeypatch.setattr(package, "detect", off_by_a_degree)
    # Balanced's 0.3 dB would refuse even the tuned level; with 1 dB it is kept, so the archive holds the moved plane.
    report = _compress_and_check(planted.scene, replace(CONFIG, iterations=20, max_levels=1, psnr_budget=1.0)).report
    assert calls  # the level loop asked the tilted detector
    level = report.levels[0]
    assert level.accepted and level.psnr_after > level.psnr_before
    assert _angle(level.normal, tilted.normal) > 0.1  # it moved
    assert _angle(level.normal, truth) < _angle(tilted.normal, truth) - 0.1  # towards the mirror


@pytest.mark.parametrize("count", [None, 12])
def test_fewer_than_a_hundred_gaussians(count):
    """A symmetric object of a few dozen Gaussians, where a plane and its bits weigh as much as what they save, and
    a dozen of them, too few to search."""
    scene = synthetic_scene("global", n=60, seed=1).scene
    scene = scene if count is None else scene.select(torch.arange(count))
    assert len(scene) < 100
    _compress_and_check(scene)


def test_no_symmetry():
    report = _compress_and_check(synthetic_scene("asymmetric", n=600, seed=18).scene).report
    assert not report.accepted_levels


def test_an_empty_scene_is_refused_with_a_clear_error():
    with pytest.raises(ValueError, match="no Gaussians") as caught:
        compress(GaussianScene.empty(0), config=CONFIG)
    assert caught.value.code == "empty_scene"  # the code the API answers an empty upload with


def test_the_python_doors_name_what_they_take(tmp_path):  # noqa: ANN001
    """A preset's name where a config belongs, a path where detection wants a scene: a TypeError that says what to
    pass, not an AttributeError from deep inside; an archive's bytes are taken in any bytes-like form."""
    from symgs_core import decompress, detect
    from symgs_core.export import save_scene

    scene = synthetic_scene("global", n=300, seed=1).scene
    path = tmp_path / "s.ply"
    save_scene(scene, path)
    with pytest.raises(TypeError, match=r"CompressConfig.for_preset\('small'\)"):
        compress(path, config="fast")
    with pytest.raises(TypeError, match="load_scene"):
        detect(str(path))
    archive = compress(scene, config=replace(CONFIG, use_mirrors=False)).archive
    assert len(decompress(memoryview(archive))) == len(decompress(archive)) == len(decompress(bytearray(archive)))
