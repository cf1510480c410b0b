"""The CPU tile rasterizer against the dense all-pairs reference, plus exact single-Gaussian oracles."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import textwrap

import numba
import pytest
import torch

from symgs_core.cameras import Camera
from symgs_core.render import BackendUnavailableError, RenderResult, render
from symgs_core.render._cpu import render_cpu
from symgs_core.scene import SH_REST_COUNT, GaussianScene
from tests.conftest import PROJECT_ROOT
from tests.unit._dense_reference import dense_render

ATTRIBUTES = ("means", "quats", "scales", "opacities", "sh_dc", "sh_rest")


def random_scene(n: int, sh_degree: int, seed: int, dtype: torch.dtype = torch.float64) -> GaussianScene:
    """Gaussians around the origin, seen by ``make_camera``: small ones, a few spanning many tiles, an opaque
    cluster deep enough to stop compositing early, and some behind the camera."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g, dtype=dtype) - 0.5) * torch.tensor([3.0, 2.0, 2.5], dtype=dtype)
    scales = torch.log(0.02 + 0.12 * torch.rand(n, 3, generator=g, dtype=dtype))
    opacities = 4.0 * torch.randn(n, generator=g, dtype=dtype)
    big = slice(0, n // 20)  # several tiles wide
    scales[big] = math.log(0.4)
    layers = min(12, n // 4)
    cluster = slice(n // 20, n // 20 + layers)  # stacked opaque discs in front of the centre
    means[cluster] = 0.0
    means[cluster, 1] = torch.linspace(-0.5, 0.5, layers, dtype=dtype)
    scales[cluster] = math.log(0.3)
    opacities[cluster] = 6.0
    behind = slice(n - n // 15, n)  # the camera sits at y = -4
    means[behind] = means[behind] + torch.tensor([0.0, -5.0, 0.0], dtype=dtype)
    k = SH_REST_COUNT[sh_degree]
    return GaussianScene(
        means=means,
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        scales=scales,
        opacities=opacities,
        sh_dc=0.6 * torch.randn(n, 3, generator=g, dtype=dtype),
        sh_rest=0.15 * torch.randn(n, k, 3, generator=g, dtype=dtype),
    )


def make_camera(width: int = 48, height: int = 40) -> Camera:
    cam = Camera.look_at((0.3, -4.0, 0.8), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 55.0, width, height)
    # look_at rounds R to float32; make it orthonormal in float64 so exact identities hold to float64 precision.
    u, _, vh = torch.linalg.svd(cam.R.double())
    rot = u @ vh
    t = -rot @ torch.tensor([0.3, -4.0, 0.8], dtype=torch.float64)
    # An off-centre principal point, as real cameras have.
    return Camera(rot, t, cam.fx, cam.fy * 1.05, cam.cx + 1.7, cam.cy - 2.2, width, height)


def loss_weights(height: int, width: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(height, width, 3, generator=g, dtype=torch.float64),
        torch.randn(height, width, generator=g, dtype=torch.float64),
        torch.randn(height, width, generator=g, dtype=torch.float64),
    )


def weighted_loss(image, alpha, depth, weights) -> torch.Tensor:
    w_img, w_alpha, w_depth = weights
    # Depth only where something opaque was drawn: elsewhere it is a ratio of two tiny numbers.
    solid = (alpha.detach() > 0.2).double()
    return (image * w_img).sum() + (alpha * w_alpha).sum() + 0.1 * (depth * w_depth * solid).sum()


def grads_of(scene: GaussianScene, fn) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    leaves = {k: v.detach().clone().requires_grad_(True) for k, v in scene.tensors().items()}
    loss = fn(GaussianScene(**leaves))
    loss.backward()
    return loss.detach(), {k: v.grad for k, v in leaves.items()}


def _unpack(result: RenderResult) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    return result.image, result.alpha, result.depth


@pytest.mark.parametrize("sh_degree", [0, 3])
def test_tile_rasterizer_matches_dense_reference(sh_degree: int) -> None:
    scene = random_scene(240, sh_degree, seed=sh_degree)
    cam = make_camera()
    bg = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    weights = loss_weights(cam.height, cam.width, seed=7)

    result = render(scene, cam, bg, backend="cpu")
    image, alpha, depth, counts = dense_render(scene, cam, bg)
    # The scene exercises every rule: clamped alphas, early stops, culling behind the camera, many pairs.
    assert counts["clamped"] > 0 and counts["stopped_pixels"] > 0 and counts["behind_camera"] > 0
    assert counts["pairs"] > 5 * cam.width * cam.height
    assert result.num_visible < len(scene)
    torch.testing.assert_close(result.image, image, rtol=0, atol=1e-10)
    torch.testing.assert_close(result.alpha, alpha, rtol=0, atol=1e-10)
    solid = alpha > 0.2
    torch.testing.assert_close(result.depth[solid], depth[solid], rtol=1e-9, atol=0)

    loss, grads = grads_of(scene, lambda s: weighted_loss(*_unpack(render(s, cam, bg, backend="cpu")), weights))
    ref_loss, ref_grads = grads_of(scene, lambda s: weighted_loss(*dense_render(s, cam, bg)[:3], weights))
    torch.testing.assert_close(loss, ref_loss, rtol=1e-10, atol=0)
    for name in ATTRIBUTES:
        if name == "sh_rest" and sh_degree == 0:
            continue
        got, want = grads[name], ref_grads[name]
        assert want.abs().max() > 0, name
        torch.testing.assert_close(got, want, rtol=1e-7, atol=1e-8 * float(want.abs().max()), msg=name)


def test_background_gradient_matches_reference() -> None:
    scene = random_scene(120, 0, seed=13)
    cam = make_camera()
    weights = loss_weights(cam.height, cam.width, seed=3)
    grads = []
    for draw in (lambda s, bg: _unpack(render(s, cam, bg)), lambda s, bg: dense_render(s, cam, bg)[:3]):
        bg = torch.tensor([0.3, 0.6, 0.1], dtype=torch.float64, requires_grad=True)
        weighted_loss(*draw(scene, bg), weights).backward()
        grads.append(bg.grad)
    assert grads[1].abs().min() > 1.0  # the background shows through
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-10, atol=0)


def test_float32_scene_matches_reference_closely() -> None:
    scene = random_scene(200, 1, seed=11)
    cam = make_camera()
    bg = torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64)
    result = render(scene.map(lambda t: t.float()), cam, bg.float(), backend="cpu")
    image, alpha, _, _ = dense_render(scene, cam, bg)
    assert result.image.dtype == torch.float32
    # float32 projection can flip a threshold (1/255, the 3-sigma box) for a pixel or two; nearly all match tightly.
    close = (result.image.double() - image).abs().amax(-1) < 1e-4
    assert close.float().mean() > 0.99
    assert (result.alpha.double() - alpha).abs().max() < 0.05


def test_image_does_not_depend_on_tile_size() -> None:
    scene = random_scene(150, 2, seed=3)
    cam = make_camera(37, 29)
    bg = torch.tensor([0.1, 0.0, 0.3], dtype=torch.float64)
    deg = scene.sh_degree
    base = render_cpu(scene, cam, bg, deg, tile_size=16)
    for tile in (1, 5, 8, 64):
        other = render_cpu(scene, cam, bg, deg, tile_size=tile)
        assert torch.equal(other.image, base.image) and torch.equal(other.alpha, base.alpha), tile
    _, g16 = grads_of(scene, lambda s: render_cpu(s, cam, bg, deg, tile_size=16).image.sum())
    _, g5 = grads_of(scene, lambda s: render_cpu(s, cam, bg, deg, tile_size=5).image.sum())
    for name in ATTRIBUTES:
        torch.testing.assert_close(g5[name], g16[name], rtol=1e-9, atol=1e-12, msg=name)


def test_gradients_have_the_same_bits_for_any_thread_count() -> None:
    threads = numba.config.NUMBA_NUM_THREADS
    if threads < 2:
        pytest.skip("numba has a single thread on this machine")
    scene = random_scene(150, 1, seed=12)
    cam = make_camera()
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        _, single = grads_of(scene, lambda s: render(s, cam).image.square().sum())
        numba.set_num_threads(threads)
        _, multi = grads_of(scene, lambda s: render(s, cam).image.square().sum())
    finally:
        numba.set_num_threads(before)
    for name in ATTRIBUTES:
        assert torch.equal(single[name], multi[name]), name


def _binning_oracle(means2d, radii, depths, width: int, height: int, tile: int) -> tuple[list, list[list[int]]]:
    """Each Gaussian's pixel rect and each tile's list, front to back: the definition, one Gaussian at a time."""
    rects, lists = [], [[] for _ in range(-(-width // tile) * -(-height // tile))]
    for (u, v), r in zip(means2d.tolist(), radii.tolist()):
        xs = [x for x in range(width) if abs(x + 0.5 - u) <= r]
        ys = [y for y in range(height) if abs(y + 0.5 - v) <= r]
        rects.append([xs[0], xs[-1], ys[0], ys[-1]] if r > 0 and xs and ys else [1, 0, 1, 0])
    nan_last = lambda g: (math.isnan(depths[g]), 0.0 if math.isnan(depths[g]) else depths[g], g)  # noqa: E731
    for g in sorted(range(len(rects)), key=nan_last):
        x0, x1, y0, y1 = rects[g]
        for ty in range(y0 // tile, y1 // tile + 1) if x0 <= x1 else ():
            for tx in range(x0 // tile, x1 // tile + 1):
                lists[ty * -(-width // tile) + tx].append(g)
    return rects, lists


@pytest.mark.parametrize("n", [7, 3000, 60000])  # 60000: three sorted runs to merge
def test_binning_is_the_definition_for_any_thread_count(n: int) -> None:
    import numpy as np

    from symgs_core.render import _kernels

    rng = np.random.default_rng(n)
    means = rng.uniform(-4, 4, size=(n, 2)) + rng.uniform(0, [64, 48], size=(n, 2))
    radii = np.where(rng.random(n) < 0.1, 0.0, rng.exponential(3.0, n))
    depths = rng.integers(-n // 20, n // 5 + 2, n).astype(np.float64)  # many ties: their order is the Gaussians' own
    for value, share in ((np.nan, 0.05), (-0.0, 0.02), (0.0, 0.02), (np.inf, 0.01), (-np.inf, 0.01)):
        depths[rng.random(n) < share] = value
    rects, lists = _binning_oracle(means, radii, depths, 64, 48, 16)
    for threads in (1, 2, 3, 8):
        got_rects, offsets, ids = _kernels.bin_gaussians(means, radii, depths, 64, 48, 16, threads)
        assert got_rects.tolist() == rects
        assert [ids[offsets[t] : offsets[t + 1]].tolist() for t in range(len(lists))] == lists


def test_empty_scene_renders_background() -> None:
    cam = make_camera()
    bg = torch.tensor([0.25, 0.5, 0.75])
    result = render(GaussianScene.empty(2), cam, bg)
    assert result.image.shape == (cam.height, cam.width, 3)
    assert torch.equal(result.image, bg.expand(cam.height, cam.width, 3))
    assert torch.equal(result.alpha, torch.zeros(cam.height, cam.width))
    assert result.num_visible == 0


def test_default_background_is_black_and_culled_scene_still_backpropagates() -> None:
    scene = random_scene(20, 0, seed=5, dtype=torch.float32)
    scene.means += torch.tensor([0.0, -10.0, 0.0])  # all behind the camera
    scene.means.requires_grad_(True)
    result = render(scene, make_camera())
    assert torch.equal(result.image, torch.zeros_like(result.image))
    assert result.num_visible == 0 and int(result.aux["radii"].abs().sum()) == 0
    result.image.sum().backward()
    assert torch.equal(scene.means.grad, torch.zeros_like(scene.means))


def test_non_finite_gaussians_are_culled_and_huge_ones_stay_finite() -> None:
    scene = random_scene(40, 1, seed=9)
    broken = random_scene(3, 1, seed=10)
    broken.means[0, 0] = float("nan")
    broken.scales[1] = 1e4  # exp overflows to inf
    broken.scales[2] = 30.0  # finite, but its radius is about 1e15 pixels, beyond int32
    cam = make_camera()
    result = render(GaussianScene.cat([scene, broken]), cam)
    assert torch.isfinite(result.image).all() and torch.isfinite(result.alpha).all()
    assert result.aux["radii"][-3:-1].tolist() == [0, 0] and result.aux["radii"][-1] == 2**31 - 1  # saturated
    # Dropping the two broken rows changes nothing: they were culled.
    kept = GaussianScene.cat([scene, broken.select(torch.tensor([2]))])
    assert torch.equal(render(kept, cam).image, result.image)


def test_single_gaussian_peaks_at_its_centre_with_exact_values() -> None:
    width, height, distance, sigma = 33, 31, 3.0, 0.05
    cam = Camera.look_at((0.0, -distance, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 40.0, width, height)
    opacity, dc = 0.8, torch.tensor([[0.9, -0.3, 0.2]])
    scene = GaussianScene(
        means=torch.zeros(1, 3),
        quats=torch.tensor([[0.3, -0.2, 0.5, 0.7]]),
        scales=torch.full((1, 3), math.log(sigma)),
        opacities=torch.tensor([math.log(opacity / (1 - opacity))]),
        sh_dc=dc,
        sh_rest=torch.zeros(1, 0, 3),
    )
    result = render(scene, cam)
    # The image centre (16.5, 15.5) is the centre of pixel (row 15, column 16).
    peak = divmod(int(result.alpha.argmax()), width)
    assert peak == (15, 16)
    torch.testing.assert_close(result.alpha[15, 16], torch.tensor(opacity), rtol=1e-6, atol=0)
    color = torch.clamp_min(0.28209479177387814 * dc[0] + 0.5, 0.0)
    torch.testing.assert_close(result.image[15, 16], opacity * color, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(result.depth[15, 16], torch.tensor(distance), rtol=1e-6, atol=0)
    # Isotropic: the 2D covariance is (f sigma / z)^2 + 0.3 on the diagonal. 3DGS bounds the larger eigenvalue by
    # mid + sqrt(max(0.1, mid^2 - det)), which for equal eigenvalues adds sqrt(0.1).
    var = (cam.fx * sigma / distance) ** 2 + 0.3
    assert int(result.aux["radii"][0]) == math.ceil(3 * math.sqrt(var + math.sqrt(0.1)))
    # One pixel further along the row, alpha falls as exp(-1 / (2 var)).
    torch.testing.assert_close(result.alpha[15, 17], torch.tensor(opacity * math.exp(-0.5 / var)), rtol=1e-5, atol=0)
    torch.testing.assert_close(result.alpha[15, 17], result.alpha[15, 15], rtol=1e-5, atol=0)


def test_lower_sh_degree_renders_like_truncated_coefficients() -> None:
    scene = random_scene(120, 3, seed=8)
    cam = make_camera()
    truncated = scene.with_(sh_rest=scene.sh_rest[:, :3])
    assert torch.equal(render(scene, cam, sh_degree=1).image, render(truncated, cam).image)
    assert not torch.equal(render(scene, cam, sh_degree=1).image, render(scene, cam).image)


def test_invalid_arguments_are_rejected() -> None:
    scene = random_scene(10, 1, seed=1)
    cam = make_camera()
    with pytest.raises(ValueError, match="sh_degree must be in 0..1"):
        render(scene, cam, sh_degree=2)
    with pytest.raises(ValueError, match=r"background must be an RGB tensor of shape \(3,\), got \(4,\)"):
        render(scene, cam, torch.zeros(4))
    with pytest.raises(ValueError, match="backend must be"):
        render(scene, cam, backend="opengl")  # type: ignore[arg-type]


def test_auto_backend_uses_cpu_for_cpu_tensors_and_gsplat_refuses_them() -> None:
    scene = random_scene(10, 0, seed=2)
    assert render(scene, make_camera()).aux["backend"] == "cpu"
    with pytest.raises(BackendUnavailableError, match="CUDA tensors"):
        render(scene, make_camera(), backend="gsplat")


def test_kernels_compile_without_a_writable_cache(tmp_path) -> None:
    """A read-only install: every numba cache location is unusable, so the kernels compile in memory and run."""
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("")
    package = tmp_path / "pkg"
    package.mkdir()
    source = (PROJECT_ROOT / "symgs_core" / "render" / "_kernels.py").read_text()
    (package / "_kernels.py").write_text(source)
    (package / "__pycache__").write_text("")  # numba's in-tree cache directory cannot be created
    script = textwrap.dedent(
        """
        import numpy as np
        import _kernels
        means = np.array([[4.0, 4.0]]); radii = np.array([3.0])
        rects, offsets, ids = _kernels.bin_gaussians(means, radii, np.array([2.0]), 8, 8, 4, 2)
        print(rects.tolist(), ids.tolist())
        """
    )
    env = dict(os.environ, NUMBA_CACHE_DIR=str(blocker / "numba"), XDG_CACHE_HOME=str(blocker / "xdg"),
               HOME=str(blocker / "home"), PYTHONPATH=str(package))
    done = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["[[1,", "6,", "1,", "6]]", "[0,", "0,", "0,", "0]"]


@pytest.mark.cuda
@pytest.mark.skipif(not torch.cuda.is_available(), reason="the gsplat backend needs a CUDA device")
def test_gsplat_backend_matches_cpu_backend() -> None:
    pytest.importorskip("gsplat", reason="gsplat (the 'gpu' extra) is not installed")
    scene = random_scene(240, 3, seed=4, dtype=torch.float32)
    cam = make_camera(64, 48)
    cam = Camera(cam.R.float(), cam.t.float(), cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)
    bg = torch.tensor([0.2, 0.5, 0.9])
    cpu = render(scene, cam, bg, backend="cpu")
    gpu = render(scene.to("cuda"), cam, bg.cuda())
    assert gpu.aux["backend"] == "gsplat"
    # float32 arithmetic in another order, and gsplat's alpha clamp (0.999 where 3DGS uses 0.99) changes the few
    # pixels behind a nearly opaque splat by up to about 1e-2; everywhere else the pictures agree closely.
    diff = (gpu.image.cpu() - cpu.image).abs()
    assert diff.mean() < 5e-3 and (diff < 2e-2).float().mean() > 0.98
    assert (gpu.alpha.cpu() - cpu.alpha).abs().mean() < 5e-3


def test_compiled_projection_renders_what_the_reference_renders() -> None:
    """Renders nobody differentiates take one compiled pass over the Gaussians; it agrees with the autograd path."""
    scene = random_scene(300, 3, seed=5).map(lambda t: t.float())
    cam = make_camera()
    with torch.no_grad():
        fast = render(scene, cam, backend="cpu")
    slow = render(scene.map(lambda t: t.clone().requires_grad_(True)), cam, backend="cpu")
    torch.testing.assert_close(fast.image, slow.image.detach(), rtol=0, atol=2e-5)
    torch.testing.assert_close(fast.alpha, slow.alpha.detach(), rtol=0, atol=2e-5)
    assert fast.num_visible == slow.num_visible


@pytest.mark.parametrize(("stored", "sh_degree"), [(0, 0), (1, 1), (2, 2), (3, 3), (3, 1)])
def test_compiled_projection_gradients_are_autograd_through_the_reference(stored: int, sh_degree: int) -> None:
    """The compiled projection's backward against autograd through ``project`` in float64, on the same float32
    values: every output weighted at random, every attribute's gradient, Gaussians behind the camera, beyond the
    Jacobian's clamp and with colours clamped at zero included; bands above the degree rendered get none."""
    from symgs_core.render._cpu import _project_compiled
    from symgs_core.render.projection import project

    scene = random_scene(400, stored, seed=11).map(lambda t: t.float())
    scene = scene.with_(means=scene.means * torch.tensor([4.0, 1.0, 4.0]))  # some far outside the field of view
    cam = make_camera()
    g = torch.Generator().manual_seed(3)
    weights = [torch.randn(shape, generator=g, dtype=torch.float64) for shape in ((400, 2), (400, 3), (400,),
                                                                                    (400, 3), (400,))]  # fmt: skip

    outputs = ("means2d", "conics", "depths", "colors", "opacity")
    for output, weight in zip(outputs, weights):  # one at a time: a small path is not hidden by a large one

        def loss(proj, output=output, weight=weight) -> torch.Tensor:  # noqa: ANN001
            return (getattr(proj, output).double() * weight).sum()

        _, fast = grads_of(scene, lambda s, loss=loss: loss(_project_compiled(s, cam, sh_degree)))
        _, exact = grads_of(scene.map(lambda t: t.double()), lambda s, loss=loss: loss(project(s, cam, sh_degree)))
        for name in ATTRIBUTES:
            got = fast[name]
            want = torch.zeros_like(got, dtype=torch.float64) if exact[name] is None else exact[name]
            assert got.dtype == torch.float32, (output, name)
            scale = float(want.abs().max()) if want.numel() else 0.0
            torch.testing.assert_close(got.double(), want, rtol=1e-4, atol=1e-6 * scale + 1e-12,
                                       msg=f"{name} from {output}")  # fmt: skip
    behind = cam.R.double() @ scene.means.double().T  # rows with a constant placeholder depth still get gradients
    assert (behind[2] + cam.t[2] <= cam.near).any()


def test_gaussians_no_pixel_took_get_zero_gradients_and_the_others_theirs() -> None:
    """The compiled backward skips Gaussians whose every output gradient is zero (most of a large view's): they get
    exact zeros, and every other Gaussian, whichever single output it has a gradient from, the same gradients as
    when nothing is skipped."""
    from symgs_core.render._cpu import _project_compiled

    n = 300
    scene = random_scene(n, 3, seed=12).map(lambda t: t.float())
    cam = make_camera()
    g = torch.Generator().manual_seed(4)
    shapes = ((n, 2), (n, 3), (n,), (n, 3), (n,))
    weights = [torch.randn(shape, generator=g, dtype=torch.float64) for shape in shapes]
    took = torch.arange(n) % 6  # 0: no gradient from any output; 1..5: from that output alone
    masked = [w * (took == k + 1).double().reshape(-1, *([1] * (w.dim() - 1))) for k, w in enumerate(weights)]

    def loss(ws):  # noqa: ANN001, ANN202
        outputs = ("means2d", "conics", "depths", "colors", "opacity")
        return lambda s: sum((getattr(_project_compiled(s, cam, 3), o).double() * w).sum() for o, w in zip(outputs, ws))

    _, full = grads_of(scene, loss(weights))
    _, some = grads_of(scene, loss(masked))
    for k in range(1, 6):
        alone = [w if i == k - 1 else torch.zeros_like(w) for i, w in enumerate(weights)]
        _, one = grads_of(scene, loss(alone))
        for name in ATTRIBUTES:
            assert torch.equal(some[name][took == k], one[name][took == k]), (name, k)
    for name in ATTRIBUTES:
        skipped = some[name][took == 0]
        assert torch.equal(skipped, torch.zeros_like(skipped)) and not skipped.signbit().any(), name
        assert full[name][took == 0].abs().sum() > 0, name  # they have gradients when their outputs do
