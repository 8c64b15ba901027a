"""The structured local Gaussian fields (model/gaussian_field.py, model/densify.py) and their whole chain on the toy body."""

from __future__ import annotations

import json
import math
import sys

import pytest
import torch

from avatarctl.fit.config import preset
from avatarctl.model.config import GaussianConfig, ModelConfig
from avatarctl.model.gaussian_field import NodeGaussians, eval_sh, initial_gaussians, rgb_to_sh0
from avatarctl.splat.covariance import quaternion_to_matrix, transformed_covariances


def _sphere(n: int = 12):
    """A UV sphere of radius 0.3 m: vertices [V, 3], faces [F, 3]."""
    th, ph = torch.meshgrid(torch.linspace(0.1, math.pi - 0.1, n), torch.linspace(0, 2 * math.pi, n + 1)[:-1],
                            indexing="ij")
    v = 0.3 * torch.stack([th.sin() * ph.cos(), th.cos(), th.sin() * ph.sin()], -1).reshape(-1, 3)
    f = []
    for i in range(n - 1):
        for j in range(n):
            a, b, c, d = i * n + j, i * n + (j + 1) % n, (i + 1) * n + j, (i + 1) * n + (j + 1) % n
            f += [[a, c, b], [b, c, d]]
    return v, torch.tensor(f)


def test_sh_colour_and_quaternions():
    rgb = torch.tensor([[0.2, 0.5, 0.9]])
    sh = torch.zeros(1, 4, 3)
    sh[:, 0] = rgb_to_sh0(rgb)
    d = torch.nn.functional.normalize(torch.randn(1, 3), dim=-1)
    assert torch.allclose(eval_sh(sh, d), rgb, atol=1e-6)  # degree 0 is view-independent
    sh[:, 3, 0] = 1.0  # the x-linear band: red changes with the x of the viewing direction
    left, right = eval_sh(sh, torch.tensor([[-1.0, 0, 0]])), eval_sh(sh, torch.tensor([[1.0, 0, 0]]))
    assert left[0, 0] > right[0, 0] and torch.allclose(left[0, 1:], right[0, 1:])
    q = torch.randn(50, 4)
    R = quaternion_to_matrix(q)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3).expand(50, 3, 3), atol=1e-5)
    assert torch.allclose(torch.linalg.det(R), torch.ones(50), atol=1e-5)
    assert torch.allclose(quaternion_to_matrix(torch.tensor([2.0, 0, 0, 0])), torch.eye(3))


def test_initial_gaussians_start_on_the_surface_within_their_node():
    v, f = _sphere()
    from avatarctl.model.deformer import farthest_point_sampling

    nodes = v[farthest_point_sampling(v, 40, 0)]
    hull = torch.tensor([[0.0, 0.0, 0.8]])  # off the body: no surface point is nearest to it
    rest = torch.cat([nodes, hull])
    means, log_scales = initial_gaussians(v, f, rest, 16, support_radius=0.19, seed=0)
    assert means.shape == (rest.shape[0], 16, 3) and log_scales.shape == means.shape
    world = means + rest[:, None]
    r = world[:-1].norm(dim=-1)
    assert (r > 0.27).all() and (r <= 0.3 + 1e-5).all()  # on the (faceted) sphere
    assert (means[:-1].norm(dim=-1) < 0.19).all()  # within the node's support
    assert (means[-1].norm(dim=-1) <= 0.19 / 3 + 1e-6).all()  # the hull node's ball
    again, _ = initial_gaussians(v, f, rest, 16, support_radius=0.19, seed=0)
    assert torch.equal(means, again)
    # with the hull survey's off-body cells (a loose garment's volume) the hull node starts inside them
    cell = torch.tensor([[0.0, 0.0, 0.78], [0.0, 0.05, 0.8]])
    hull_means, hull_scales = initial_gaussians(v, f, rest, 16, support_radius=0.19, seed=0, off_body=(cell, 0.05))
    inside = ((hull_means[-1] + rest[-1])[:, None, :] - cell[None]).abs().amax(-1).amin(-1)  # [K] to the nearest cell
    assert (inside <= 0.025 + 1e-6).all()
    assert hull_scales[-1].exp().max() < 0.05


def _fields(N: int = 3, K: int = 5, E: int = 4, sh_degree: int = 1) -> NodeGaussians:
    torch.manual_seed(0)
    cfg = GaussianConfig(per_node=K, feature_dim=6, decoder_width=8, sh_degree=sh_degree, shading="none")
    return NodeGaussians(cfg, N, E, 0.05 * torch.randn(N, K, 3), torch.full((N, K, 3), math.log(0.02)))


def test_posed_gaussians_follow_the_node_transforms():
    g = _fields()
    B, N, K = 2, 3, 5
    angle = 0.7
    rot = torch.tensor([[math.cos(angle), -math.sin(angle), 0], [math.sin(angle), math.cos(angle), 0], [0, 0, 1.0]])
    T = torch.eye(4).repeat(B, N, 1, 1)
    T[1, :, :3, :3] = rot
    centers = torch.randn(B, N, 3)
    posed = g(T, centers, torch.zeros(B, N, 4))
    assert posed.means.shape == (B, N * K, 3) and posed.covars.shape == (B, N * K, 3, 3)
    # x_ik = n_i + A_i mu_ik (Eq. 4 read backwards); Sigma = A R S^2 R^T A^T
    local = g.means.detach()
    assert torch.allclose(posed.means[0], (centers[0][:, None] + local).reshape(-1, 3), atol=1e-6)
    assert torch.allclose(posed.means[1], (centers[1][:, None] + local @ rot.T).reshape(-1, 3), atol=1e-6)
    assert torch.allclose(posed.covars[1], rot @ posed.covars[0] @ rot.T, atol=1e-7)
    assert torch.allclose(posed.covars[0], torch.eye(3).expand(N * K, 3, 3) * 0.02 ** 2, atol=1e-9)
    # the decoder's last layer starts at zero: e_i changes nothing yet; once trained it does (the detail level)
    e = torch.randn(B, N, 4)
    assert torch.allclose(g(T, centers, e).opacities, posed.opacities)
    with torch.no_grad():
        g.decoder.layers[-1].weight.normal_()
    a, b = g(T, centers, e), g(T, centers, torch.zeros(B, N, 4))
    assert not torch.allclose(a.means, b.means) and not torch.allclose(a.opacities, b.opacities)


def test_view_dependent_colour_turns_with_the_node():
    g = _fields(N=1, K=1)
    with torch.no_grad():
        g.sh[0, 0, 3, 0] = 1.0  # red depends on the local x of the viewing direction
    rot = torch.tensor([[-1.0, 0, 0], [0, -1.0, 0], [0, 0, 1.0]])  # the node turned by 180 degrees about z
    T = torch.eye(4).repeat(2, 1, 1, 1)
    T[1, 0, :3, :3] = rot
    posed = g(T, torch.zeros(2, 1, 3), torch.zeros(2, 1, 4))
    cam = posed.means[0, 0] + torch.tensor([5.0, 0, 0])
    cam1 = posed.means[1, 0] + torch.tensor([-5.0, 0, 0])  # the same side of the turned node
    assert torch.allclose(posed.colors(0, cam), posed.colors(1, cam1), atol=1e-5)
    assert not torch.allclose(posed.colors(0, cam), posed.colors(1, -cam1 + 2 * posed.means[1, 0]))


def test_irradiance_shading_turns_with_the_node_and_starts_neutral():
    """shading "irradiance": c = E(A_i n_ik) (0.5 + SH) with E(m) = max(0, 1 + sum_j l_j Y_j(m)); l = 0 at the start."""
    from avatarctl.model.gaussian_field import irradiance_basis, shade

    torch.manual_seed(0)
    N, K, E = 2, 3, 4
    cfg = GaussianConfig(per_node=K, feature_dim=6, decoder_width=8, shading="irradiance")
    normals = torch.nn.functional.normalize(torch.randn(N, K, 3), dim=-1)
    g = NodeGaussians(cfg, N, E, 0.05 * torch.randn(N, K, 3), torch.full((N, K, 3), math.log(0.02)),
                      init_normals=normals)
    plain = NodeGaussians(GaussianConfig(per_node=K, feature_dim=6, decoder_width=8, shading="none"), N, E,
                          g.means.detach(), g.log_scales.detach())
    plain.load_state_dict({k: v for k, v in g.state_dict().items() if k not in ("normals", "light")})
    with torch.no_grad():
        g.sh.uniform_(-1, 1)
        plain.sh.copy_(g.sh)
    rot = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 degrees about z
    T = torch.eye(4).repeat(2, N, 1, 1)
    T[1, :, :3, :3] = rot
    args = (T, torch.zeros(2, N, 3), torch.zeros(2, N, E))
    assert torch.allclose(g(*args).sh, plain(*args).sh)  # l = 0: the unshaded colours
    with torch.no_grad():
        g.light.normal_(0, 0.3)
    posed, ref = g(*args), plain(*args)
    for b, A in ((0, torch.eye(3)), (1, rot)):
        m = normals @ A.T  # the world normal: A_i n_ik
        shading = (1 + irradiance_basis(m) @ g.light.detach()).clamp(min=0)  # [N, K, 3]
        want = shading.reshape(-1, 3) * ref.colors(b, torch.zeros(3))
        assert torch.allclose(posed.colors(b, torch.zeros(3)), want, atol=1e-5)
    assert not torch.allclose(posed.colors(0, torch.zeros(3)), posed.colors(1, torch.zeros(3)))  # turned: shaded anew
    # the view-dependent bands are scaled alike (degree 1): c = E (0.5 + SH(d))
    sh1 = torch.randn(1, 1, 1, 4, 3)
    lin = torch.eye(3).expand(1, 1, 3, 3)
    n1, l1 = torch.tensor([[[0.0, 0.0, 1.0]]]), torch.randn(8, 3)
    d = torch.nn.functional.normalize(torch.randn(1, 1, 1, 3), dim=-1)
    e1 = (1 + irradiance_basis(n1[0, 0]) @ l1).clamp(min=0)
    assert torch.allclose(eval_sh(shade(sh1, lin, n1, l1), d), e1 * eval_sh(sh1, d), atol=1e-5)
    # the light trains at the colours' rate; the normals are fixed (a buffer, saved with the weights)
    assert any(p is g.light for p in g.gaussian_parameters()["lr_colors"])
    assert "normals" in dict(g.named_buffers()) and "normals" in g.state_dict()
    with pytest.raises(ValueError, match="initial normals"):
        NodeGaussians(cfg, N, E, g.means.detach(), g.log_scales.detach())


def test_initial_normals_are_the_templates_vertex_normals():
    from avatarctl.model.gaussian_field import initial_normals

    v, f = _sphere()
    d = torch.nn.functional.normalize(torch.randn(64, 3) * torch.tensor([1.0, 0.5, 1.0]), dim=-1)  # off the poles (y)
    pts = 0.32 * d  # just outside the sphere of radius 0.3
    n = initial_normals(v, f, pts)
    assert torch.allclose(n.norm(dim=-1), torch.ones(64), atol=1e-5)
    cos = torch.nn.functional.cosine_similarity(n, d, dim=-1)
    assert (cos < -0.95).all()  # radial; inward here because this sphere's faces are wound inward
    assert torch.allclose(initial_normals(v, f.flip(-1), pts), -n)  # the winding gives the side


def test_relocation_moves_dead_gaussians_onto_live_ones_of_their_node():
    from avatarctl.model.densify import relocate_dead

    g = _fields(N=2, K=4)
    opt = torch.optim.Adam(g.parameters(), lr=1e-3)
    for p in g.parameters():
        p.grad = torch.ones_like(p)
    opt.step()
    with torch.no_grad():
        g.opacity_logits.copy_(torch.logit(torch.tensor([[0.001, 0.5, 0.001, 0.3], [0.5, 0.5, 0.5, 0.5]])))
    before = {n: p.detach().clone() for n, p in g.named_parameters()}
    moved = relocate_dead(g, opt, min_opacity=0.005, seed=0, step=100)
    assert moved == 2
    op = torch.sigmoid(g.opacity_logits.detach())
    assert (op > 0.005).all()
    assert torch.equal(g.means[1], before["means"][1]) and torch.equal(op[1], torch.full((4,), 0.5))  # node 1 alive
    for k in (0, 2):  # each copy came from a live Gaussian of node 0 (features, scales equal to one of them)
        src = [j for j in (1, 3) if torch.equal(g.features[0, k], before["features"][0, j])]
        assert src and torch.equal(g.log_scales[0, k], before["log_scales"][0, src[0]])
        assert torch.equal(opt.state[g.means]["exp_avg"][0, k], torch.zeros(3))
    # a source shared by n copies keeps the coverage 1 - (1 - o)^(1/n) each: together they cover what it covered
    o = {1: 0.5, 3: 0.3}
    for j in (1, 3):
        n = 1 + sum(torch.equal(g.features[0, k], before["features"][0, j]) for k in (0, 2))
        assert math.isclose(float(op[0, j]), 1 - (1 - o[j]) ** (1 / n), rel_tol=1e-5)
    # deterministic in (seed, step)
    g2 = _fields(N=2, K=4)
    g2.load_state_dict({n: before[n] for n in before})
    relocate_dead(g2, torch.optim.Adam(g2.parameters()), min_opacity=0.005, seed=0, step=100)
    assert all(torch.equal(a, b) for a, b in zip(g.parameters(), g2.parameters()))


def test_relocated_gaussians_take_their_sources_normal():
    from avatarctl.model.densify import relocate_dead

    torch.manual_seed(0)
    N, K = 2, 4
    cfg = GaussianConfig(per_node=K, feature_dim=6, decoder_width=8, shading="irradiance")
    g = NodeGaussians(cfg, N, 4, 0.05 * torch.randn(N, K, 3), torch.full((N, K, 3), math.log(0.02)),
                      init_normals=torch.nn.functional.normalize(torch.randn(N, K, 3), dim=-1))
    with torch.no_grad():
        g.opacity_logits.copy_(torch.logit(torch.tensor([[0.001, 0.5, 0.001, 0.3], [0.5, 0.5, 0.5, 0.5]])))
    before = {n: p.detach().clone() for n, p in g.state_dict().items()}
    assert relocate_dead(g, torch.optim.Adam(g.parameters()), min_opacity=0.005, seed=0, step=100) == 2
    for k in (0, 2):
        src = [j for j in (1, 3) if torch.equal(g.features[0, k], before["features"][0, j])]
        assert src and torch.equal(g.normals[0, k], before["normals"][0, src[0]])
    assert torch.equal(g.normals[1], before["normals"][1])


def test_model_config_keeps_the_gaussian_options_in_their_own_config():
    from avatarctl.errors import InputError
    from avatarctl.fit.config import FitConfig, resolve_fit_config

    cfg = resolve_fit_config("cpu", overrides=["model.field=gaussians", "model.gaussians.per_node=64"])
    assert cfg.model.gaussians.per_node == 64 and not cfg.model.uses_occupancy and not cfg.model.ray_marched
    assert FitConfig.from_json(cfg.to_json()) == cfg
    assert ModelConfig.from_json({k: v for k, v in ModelConfig().to_json().items() if k != "gaussians"}) == ModelConfig()
    with pytest.raises(InputError, match="per_node"):
        resolve_fit_config("cpu", overrides=["model.gaussians.per_node=0"])
    with pytest.raises(InputError, match="did you mean 'model.gaussians.per_node'"):
        resolve_fit_config("cpu", overrides=["model.gaussians.per_nod=3"])
    with pytest.raises(InputError, match="slrf variant"):
        resolve_fit_config("cpu", ablation="lbs-baseline", overrides=["model.field=gaussians"])


_TOY_SETS = ("model.field=gaussians", "model.gaussians.per_node=24", "val_every=0", "log_every=2", "checkpoint_every=3")
_TOY_MODEL = {"gaussians": {"relocate_every": 2}}  # a fixed setting: from Python


def _toy_project(tmp_path, monkeypatch, name: str = "proj"):
    """(capture, project): the toy body's capture ingested (anny unavailable, as on a machine without it)."""
    from fixtures.toy_capture import make_toy_capture

    from avatarctl.stages import ingest
    from avatarctl.stages.ingest import IngestConfig

    monkeypatch.setitem(sys.modules, "anny", None)
    cap, proj = make_toy_capture(tmp_path / "cap"), tmp_path / name
    ingest.run(proj, IngestConfig(capture=cap, project=proj))
    return cap, proj


def test_fit_render_eval_with_gaussian_fields_on_the_toy_body(tmp_path, monkeypatch):
    """The chain on the rasterized field: fit (image crops, L1 + D-SSIM), resume bitwise, render, eval."""
    from avatarctl.fit.checkpoint import read_checkpoint
    from avatarctl.project import Project
    from avatarctl.stages import evaluate, fit, ingest, render
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.fit import FitRequest
    from avatarctl.stages.ingest import IngestConfig
    from avatarctl.stages.render import RenderConfig

    cap, proj = _toy_project(tmp_path, monkeypatch)
    sets = _TOY_SETS
    fr = fit.run(proj, FitRequest(preset="micro", iters=6, overrides=sets, model_settings=_TOY_MODEL, device="cpu"),
                 handle_sigint=False)
    assert fr.step == 6 and math.isfinite(fr.losses["total"]) and fr.val is not None and 0 < fr.val.psnr < 100
    straight = read_checkpoint(Project.open(proj).paths.latest_checkpoint)["model"]
    # the same 6 steps as 3 + resume 3: bitwise (relocation at steps 2, 4, 6 included)
    proj2 = tmp_path / "proj2"
    ingest.run(proj2, IngestConfig(capture=cap, project=proj2))
    fit.run(proj2, FitRequest(preset="micro", iters=3, overrides=sets, model_settings=_TOY_MODEL, device="cpu"),
            handle_sigint=False)
    fit.run(proj2, FitRequest(iters=6, resume=True, device="cpu"), handle_sigint=False)
    resumed = read_checkpoint(Project.open(proj2).paths.latest_checkpoint)["model"]
    assert straight.keys() == resumed.keys() and all(torch.equal(straight[k], resumed[k]) for k in straight)
    rr = render.run(proj, RenderConfig(name="toy", frames="0:4:3", device="cpu"))
    assert len(rr.images) == 2 and rr.video.is_file()
    er = evaluate.run(proj, EvalConfig(split="novel_view", device="cpu"))
    assert er.metrics.images == 6 and 0 < er.psnr < 100
    # export: a posed mesh from the Gaussians' density and the splats of the same frame
    from avatarctl.stages import export
    from avatarctl.stages.export import ExportConfig

    xr = export.run(proj, ExportConfig(frames="0", formats=("glb", "splat"), skinned=False, voxel=0.02, device="cpu"))
    assert xr.meshes and xr.meshes[0].faces > 100 and (xr.out_dir / "splats").is_dir()
    from avatarctl.export.view_colours import VIEW_RULE

    record = json.loads((xr.out_dir / "export.json").read_text())
    assert record["surface"]["colour"] == VIEW_RULE, "a Gaussian avatar's mesh is coloured from its images"


def _covariances_against_twin(device: str) -> None:
    gen = torch.Generator().manual_seed(0)
    A = torch.randn(2, 5, 3, 3, generator=gen)
    quats, log_scales = torch.randn(5, 7, 4, generator=gen), torch.randn(5, 7, 3, generator=gen) - 3.0
    quats[0, 0] = 0.0  # the norm's clamp
    twin = transformed_covariances(A.double(), quats.double(), log_scales.double())  # float64: the torch path
    with torch.no_grad():
        fused = transformed_covariances(A.to(device), quats.to(device), log_scales.to(device)).cpu()
    assert fused.shape == (2, 5, 7, 3, 3) and fused.dtype == torch.float32
    assert torch.allclose(fused.double(), twin, rtol=1e-5, atol=1e-6 * float(twin.abs().max()))


def test_covariance_kernel_matches_the_torch_twin(monkeypatch):
    """`transformed_covariances` without gradients (the Warp kernel) = its torch twin; with gradients to keep it
    takes the torch path (the kernel has no backward)."""
    _covariances_against_twin("cpu")
    import warp

    q = torch.randn(2, 3, 4, requires_grad=True)
    monkeypatch.setattr(warp, "launch", None)  # the kernel path would fail
    transformed_covariances(torch.randn(1, 2, 3, 3), q, torch.zeros(2, 3, 3)).sum().backward()
    assert q.grad is not None


@pytest.mark.gpu
def test_cuda_covariance_kernel_matches_the_torch_twin():
    _covariances_against_twin("cuda")


@pytest.mark.gpu
def test_fit_eval_with_gaussian_fields_on_cuda(tmp_path, monkeypatch):
    """The same chain on CUDA: fit (image crops, relocation, a checkpoint), then eval (render_view), on the GPU."""
    from avatarctl.stages import evaluate, fit
    from avatarctl.stages.evaluate import EvalConfig
    from avatarctl.stages.fit import FitRequest

    _, proj = _toy_project(tmp_path, monkeypatch)
    fr = fit.run(proj, FitRequest(preset="micro", iters=4, overrides=_TOY_SETS, model_settings=_TOY_MODEL,
                                  device="cuda"), handle_sigint=False)
    assert fr.step == 4 and math.isfinite(fr.losses["total"])
    er = evaluate.run(proj, EvalConfig(split="novel_view", device="cuda"))
    assert er.metrics.images == 6 and 0 < er.psnr < 100


def test_splat_ply_holds_the_posed_gaussians_in_the_world_frame(tmp_path):
    """The 3DGS .ply (export/splat_ply.py), read back by trimesh: the same centres, covariances, opacities, and the
    same view-dependent colour once the local-frame SH band is turned into the world frame."""
    trimesh = pytest.importorskip("trimesh")
    from avatarctl.export.splat_ply import splat_arrays, write_splat_ply
    from avatarctl.splat.density import SH_C0, SH_C1

    g = _fields(N=2, K=3)
    with torch.no_grad():
        g.sh.normal_()
        g.quats.normal_()
    T = torch.eye(4).repeat(1, 2, 1, 1)
    T[0, 1, :3, :3] = quaternion_to_matrix(torch.tensor([0.8, 0.1, -0.5, 0.3]))
    posed = g(T, torch.randn(1, 2, 3), torch.zeros(1, 2, 4))
    cols = splat_arrays(posed.means[0], posed.covars[0], posed.sh[0], posed.opacities[0], T[0, :, :3, :3], 3)
    v = trimesh.load(write_splat_ply(tmp_path / "f.ply", cols, 0.1)).metadata["_ply_raw"]["vertex"]["data"]
    col = lambda n: torch.tensor(v[n], dtype=torch.float64)  # noqa: E731
    xyz = torch.stack([col("x"), col("y"), col("z")], -1)
    assert torch.allclose(xyz, posed.means[0].double(), atol=1e-6)
    assert torch.allclose(torch.sigmoid(col("opacity")), posed.opacities[0].double(), atol=1e-5)
    R = quaternion_to_matrix(torch.stack([col(f"rot_{i}") for i in range(4)], -1))
    S = torch.stack([col(f"scale_{i}") for i in range(3)], -1).exp()
    cov = R @ torch.diag_embed(S ** 2) @ R.transpose(-1, -2)
    assert torch.allclose(cov, posed.covars[0].double(), atol=1e-9, rtol=1e-4)
    cam = torch.tensor([2.0, -1.0, 3.0])
    d = torch.nn.functional.normalize(xyz - cam.double(), dim=-1)
    rest = torch.stack([col(f"f_rest_{i}") for i in range(45)], -1).reshape(-1, 3, 15)  # channel-major
    dc = torch.stack([col(f"f_dc_{i}") for i in range(3)], -1)
    rgb = 0.5 + SH_C0 * dc + SH_C1 * (-d[:, 1:2] * rest[..., 0] + d[:, 2:3] * rest[..., 1] - d[:, 0:1] * rest[..., 2])
    assert torch.allclose(rgb.clamp(min=0), posed.colors(0, cam).double(), atol=1e-5)


def _density_against_twin(device: str) -> None:
    from avatarctl.splat.density import gaussian_field_at, gaussian_field_at_torch

    gen = torch.Generator().manual_seed(0)
    G, P = 300, 1500
    means = torch.rand(G, 3, generator=gen) * 0.5
    covars = transformed_covariances(torch.eye(3).expand(1, G, 3, 3), torch.randn(G, 1, 4, generator=gen),
                                     torch.randn(G, 1, 3, generator=gen) * 0.3 - 3.5)[0, :, 0]
    weights = torch.rand(G, generator=gen) * 50
    for S in (1, 4):  # view-independent colours; degree 1 with a direction map per Gaussian
        sh = torch.randn(G, S, 3, generator=gen)
        maps = torch.randn(G, 3, 3, generator=gen) if S == 4 else None
        pts = torch.rand(P, 3, generator=gen) * 0.7 - 0.1  # some beyond every Gaussian's reach
        dirs = torch.nn.functional.normalize(torch.randn(P, 3, generator=gen), dim=-1)
        ref_rgb, ref_sigma = gaussian_field_at_torch(*(t.double() for t in (pts, dirs, means, covars, weights, sh)),
                                                     None if maps is None else maps.double())
        args = [t.to(device) for t in (pts, dirs, means, covars, weights, sh)]
        rgb, sigma = gaussian_field_at(*args, None if maps is None else maps.to(device))
        hit = ref_sigma > 1e-3
        assert 100 < int(hit.sum()) < P and int((ref_sigma == 0).sum()) > 10
        assert torch.allclose(sigma.cpu().double(), ref_sigma, rtol=1e-5, atol=1e-6)
        assert torch.allclose(rgb.cpu().double()[hit], ref_rgb[hit], atol=1e-5)


def test_density_kernels_match_the_torch_twin():
    """`splat.density.gaussian_field_at` (Gaussians binned into cells, one thread per point) = its dense twin."""
    _density_against_twin("cpu")


def test_density_cells_grow_coarser_when_the_lists_would_be_too_long(monkeypatch):
    """Huge Gaussians (floaters) cover many cells: past MAX_ENTRIES / MAX_CELLS the cells grow coarser, and the field
    stays the twin's."""
    import warp

    import avatarctl.splat.density as density

    monkeypatch.setattr(density, "MAX_ENTRIES", 3_000)
    monkeypatch.setattr(density, "MAX_CELLS", 5_000)
    launch, counted = warp.launch, []
    monkeypatch.setattr(warp, "launch", lambda kernel, *a, **k: counted.append(kernel.key) or launch(kernel, *a, **k))
    _density_against_twin("cpu")
    assert counted.count("count_cells") > 2  # two calls; at least one counted again with coarser cells


@pytest.mark.gpu
def test_cuda_density_kernels_match_the_torch_twin():
    _density_against_twin("cuda")


def test_density_query_of_the_gaussians_for_mesh_export():
    """`SlrfAvatar.query` on the Gaussian field = the sum over every Gaussian within its cut-off (brute force), and a
    ray through an isotropic Gaussian's centre accumulates the optical depth -ln(1 - o), so its opacity there is o,
    as the rasterizer draws the splat's centre."""
    from avatarctl.body.toy import sphere_template, toy_joint_transforms
    from avatarctl.model.avatar import FrameConditioning, SlrfAvatar
    from avatarctl.splat.density import CUTOFF

    cfg = preset("cpu").model.with_(field="gaussians", num_nodes=64, hull={"nodes": 0}, pose_refine={"enabled": False},
                                    cvae_width=32, gaussians=GaussianConfig(per_node=16))
    torch.manual_seed(0)
    model = SlrfAvatar(cfg, sphere_template(), num_frames=1)
    M, feats = toy_joint_transforms(torch.tensor([0.3]))
    state = model.node_state(FrameConditioning(M, feats, torch.zeros(1), torch.zeros(1, dtype=torch.long)), "mean")
    pts = 0.35 * torch.nn.functional.normalize(torch.randn(200, 3), dim=-1)
    dirs = torch.nn.functional.normalize(torch.randn(200, 3), dim=-1)
    with torch.no_grad():
        rgb, sigma, _ = model.query(pts, dirs, torch.zeros(200, dtype=torch.long), state)
        posed = model.posed_gaussians(state)
        d = pts[:, None] - posed.means[0][None]
        q = torch.einsum("pgi,gij,pgj->pg", d, torch.linalg.inv(posed.covars[0]), d)
        s = torch.linalg.det(posed.covars[0]) ** (1 / 6)
        tau = -torch.log1p(-posed.opacities[0].clamp(max=0.99))
        brute = (tau / (math.sqrt(2 * math.pi) * s) * torch.exp(-0.5 * q) * (q <= CUTOFF ** 2)).sum(1)
    assert sigma.shape == (200,) and rgb.shape == (200, 3) and (sigma > 0).sum() > 20
    assert torch.allclose(sigma, brute, rtol=1e-4, atol=1e-6)
    with torch.no_grad():  # one isotropic Gaussian left (o = 0.5): the line integral through its centre is ln 2
        model.fields.opacity_logits.fill_(-30.0)
        model.fields.opacity_logits[0, 0] = 0.0
        model.fields.quats[0, 0] = torch.tensor([0.9, 0.1, 0.3, -0.2])
        model.fields.log_scales[0, 0] = math.log(0.01)
        c = model.posed_gaussians(state).means[0, 0]
        A = state.transforms[0, 0, :3, :3]
        s_world = 0.01 * torch.linalg.det(A) ** (1 / 3)  # A is a rotation up to blending: isotropic stays so
        t = torch.linspace(-0.1, 0.1, 2001)
        line = c + t[:, None] * torch.tensor([0.0, 0.6, 0.8])
        _, sig, _ = model.query(line, line * 0, torch.zeros(2001, dtype=torch.long), state)
    depth = float(torch.trapezoid(sig, t))
    assert abs(depth - math.log(2.0)) < 0.01 * (1 + float(abs(s_world - 0.01) / 0.01))
    assert abs((1.0 - math.exp(-depth)) - 0.5) < 0.01  # the opacity a ray through the centre sees: o



def test_mask_border_band_is_left_out_of_the_image_loss():
    """`mask_border_px`: a target wrong only within 1 px of the mask's outline costs no L1 and no mask term, and
    far less than plain; 0 gives the plain loss; a wrong pixel farther in still counts."""
    from avatarctl.model.losses import image_reconstruction_loss, mask_border_weight

    g = torch.Generator().manual_seed(0)
    mask = torch.zeros(24, 20)
    mask[5:19, 6:15] = 1
    w = mask_border_weight(mask, 1)
    assert w.shape == mask.shape and w[12, 10] == 1 and w[0, 0] == 1
    assert w[5, 10] == 0 and w[4, 10] == 0 and w[3, 10] == 1 and w[6, 10] == 1  # 1 px either side of the outline
    assert mask_border_weight(torch.ones(6, 6), 1).eq(1).all()  # the crop's own edge is no outline
    assert int((mask_border_weight(mask, 2) == 0).sum()) > int((w == 0).sum())
    rgb = torch.rand(24, 20, 3, generator=g)
    wrong = rgb.clone()
    wrong[w == 0] = 1 - wrong[w == 0]  # the outline's pixels mislabelled, the avatar's alpha the other way there
    alpha = mask.clone()
    alpha[w == 0] = 1 - alpha[w == 0]

    def loss(target, ssim=0.1, border=1):
        return float(image_reconstruction_loss([rgb], [target], [alpha], [mask], ssim, 0.1, border_px=border)[0])

    assert loss(wrong, ssim=0.0) < 1e-3 < 100 < loss(wrong, ssim=0.0, border=0)  # L1 and the mask term: not seen
    assert loss(wrong) < 0.25 * loss(wrong, border=0)  # the SSIM windows beside the outline still read it
    plain = image_reconstruction_loss([rgb], [rgb], [mask], [mask], 0.1, 0.1)[0]
    assert float(plain) == float(image_reconstruction_loss([rgb], [rgb], [mask], [mask], 0.1, 0.1, border_px=0)[0])
    inside = rgb.clone()
    inside[12, 10] = 1 - inside[12, 10]
    assert loss(inside) > loss(rgb) + 1.0


def test_mask_border_auto_is_decided_from_the_masks_source():
    """`mask_border_px = "auto"` (cpu): 1 px where the masks are estimated and there are two training views or more,
    0 where they are the capture's truth or from one view; a model cannot train on "auto"; --set takes a number or
    auto."""
    from avatarctl.fit.config import apply_overrides, preset
    from avatarctl.model.config import GaussianConfig

    auto = GaussianConfig(mask_border_px="auto")
    assert auto.resolved(False, 3).border_px == 1 and auto.resolved(True, 3).border_px == 0
    assert auto.resolved(False, 1).border_px == 0  # one view: the outline is the shape's only measure
    assert GaussianConfig(mask_border_px=2).resolved(True, 1).border_px == 2  # a number stays
    with pytest.raises(ValueError, match="decided from the capture"):
        auto.border_px
    with pytest.raises(ValueError, match="mask_border_px"):
        GaussianConfig(mask_border_px=-1)
    cfg = preset("cpu")
    assert cfg.model.gaussians.mask_border_px == "auto" and preset("paper").model.gaussians.mask_border_px == 0
    assert apply_overrides(cfg, ["model.gaussians.mask_border_px=2"]).model.gaussians.mask_border_px == 2
    paper = apply_overrides(preset("paper"), ["model.field=gaussians", "model.gaussians.mask_border_px=auto"])
    assert paper.model.gaussians.mask_border_px == "auto"
