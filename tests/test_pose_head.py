"""The GDR-Net-like pose head: encodings, crops, dense targets, network, losses and decoders."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

torch = pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")

import torch.nn.functional as F  # noqa: E402

from bopsurg.models.pose import (  # noqa: E402
    GdrPoseNet,
    PoseConfig,
    SiteRoi,
    XyzNormaliser,
    allo_to_ego,
    crop,
    dzi_boxes,
    ego_to_allo,
    farthest_point_sampling,
    gdr_losses,
    mask_probability,
    matrix_from_rot6d,
    mean_pose,
    nearest_rotation,
    pnp_ransac_from_output,
    pose_from_output,
    ray_rotation,
    roi_coord_2d,
    rot6d_from_matrix,
    site_decode,
    site_encode,
    xyz_from_depth,
    xyz_to_region,
)

D64 = torch.float64
IMAGE_HW = (480, 640)


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """One intra-op thread: on a shared 2-core machine two OpenMP threads measured up to 200×
    slower than one (spinning at barriers while another process holds a core)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def _rotations(n: int, seed: int, dtype: torch.dtype = D64) -> torch.Tensor:
    return torch.as_tensor(Rotation.random(n, random_state=seed).as_matrix(), dtype=dtype)


def _intrinsics(n: int, dtype: torch.dtype = D64) -> torch.Tensor:
    K = torch.tensor([[500.0, 0.0, 320.5], [0.0, 510.0, 240.25], [0.0, 0.0, 1.0]], dtype=dtype)
    return K.expand(n, 3, 3).clone()


def _translations(n: int, seed: int, dtype: torch.dtype = D64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    xy = (torch.rand(n, 2, generator=g, dtype=dtype) - 0.5) * 60.0
    z = 150.0 + 100.0 * torch.rand(n, 1, generator=g, dtype=dtype)
    return torch.cat([xy, z], dim=1)


def _arc(n: int = 200, radius: float = 10.0) -> torch.Tensor:
    """A half-circle needle centreline in the xy plane, mm (bbox centre at the origin)."""
    a = torch.linspace(0.0, np.pi, n, dtype=D64)
    pts = torch.stack([radius * torch.cos(a), radius * torch.sin(a), torch.zeros_like(a)], 1)
    return pts - torch.tensor([0.0, radius / 2, 0.0], dtype=D64)


def _rot_err_deg(A: np.ndarray, B: np.ndarray) -> float:
    c = (np.trace(A @ B.T) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


# --- config ------------------------------------------------------------------------------------


def test_config_presets_and_dict_round_trip():
    assert PoseConfig() == PoseConfig.preset("cpu")
    assert PoseConfig().roi_out == 32
    paper = PoseConfig.preset("paper")
    assert (paper.roi_in, paper.num_regions, paper.blocks) == (256, 64, (3, 4, 6, 3))
    assert PoseConfig.from_dict(paper.to_dict()) == paper
    with pytest.raises(ValueError, match="'bogus'"):
        PoseConfig.from_dict({**paper.to_dict(), "bogus": 1})
    with pytest.raises(ValueError, match="multiple of 32"):
        PoseConfig(roi_in=100)
    with pytest.raises(ValueError, match="preset"):
        PoseConfig.preset("huge")


# --- rotations and translations ----------------------------------------------------------------


def test_rot6d_round_trip_on_random_rotations():
    R = _rotations(32, seed=0)
    assert torch.allclose(matrix_from_rot6d(rot6d_from_matrix(R)), R, atol=1e-12)
    # any (non-degenerate) 6D code decodes to a proper rotation
    x = rot6d_from_matrix(R) * 3.0 + 0.1 * torch.randn(32, 6, dtype=D64)
    Rx = matrix_from_rot6d(x)
    eye = torch.eye(3, dtype=D64).expand(32, 3, 3)
    assert torch.allclose(Rx.transpose(1, 2) @ Rx, eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(Rx), torch.ones(32, dtype=D64))


def test_allo_ego_round_trip_and_ray_rotation():
    R, t = _rotations(16, seed=1), _translations(16, seed=1)
    assert torch.allclose(ego_to_allo(allo_to_ego(R, t), t), R, atol=1e-12)
    R_c = ray_rotation(t)
    e_z = torch.tensor([0.0, 0.0, 1.0], dtype=D64)
    assert torch.allclose(R_c @ e_z, t / t.norm(dim=1, keepdim=True), atol=1e-12)
    # the rotation axis lies in the image plane (no roll about the ray)
    axis = torch.as_tensor(Rotation.from_matrix(R_c.numpy()).as_rotvec())
    assert torch.allclose(axis[:, 2], torch.zeros(16, dtype=D64), atol=1e-12)
    # on the optical axis R_c = I, and it stays smooth (finite gradient) there
    t_axis = torch.tensor([[0.0, 0.0, 200.0], [1e-9, -1e-9, 50.0]], dtype=D64, requires_grad=True)
    assert torch.allclose(ray_rotation(t_axis), torch.eye(3, dtype=D64).expand(2, 3, 3))
    ray_rotation(t_axis).sum().backward()
    assert torch.isfinite(t_axis.grad).all()
    behind = ray_rotation(torch.tensor([[0.0, 0.0, -5.0]], dtype=D64))
    assert torch.allclose(behind @ e_z, -e_z)


def test_site_round_trip():
    n = 8
    t, K = _translations(n, seed=2), _intrinsics(n)
    g = torch.Generator().manual_seed(2)
    centre = 100.0 + 300.0 * torch.rand(n, 2, generator=g, dtype=D64)
    wh = 20.0 + 80.0 * torch.rand(n, 2, generator=g, dtype=D64)
    side = 1.5 * wh.max(dim=1).values
    roi = SiteRoi(K, centre, wh, side, 32, 1000.0)
    site = site_encode(t, roi)
    assert torch.allclose(site[:, 2], t[:, 2] * side / 32 / 1000.0)
    assert torch.allclose(site_decode(site, roi), t, atol=1e-10)


def test_pose_from_output_recovers_gt_from_its_encodings():
    cfg = PoseConfig.preset("test")
    n = 6
    R, t, K = _rotations(n, seed=3), _translations(n, seed=3), _intrinsics(n)
    centre = torch.full((n, 2), 300.0, dtype=D64)
    wh = torch.tensor([40.0, 30.0], dtype=D64).expand(n, 2)
    side = torch.full((n,), 60.0, dtype=D64)
    out = {
        "rot6d": rot6d_from_matrix(ego_to_allo(R, t)),
        "site": site_encode(t, SiteRoi(K, centre, wh, side, cfg.roi_out, cfg.z_unit_mm)),
    }
    R_est, t_est = pose_from_output(out, K, centre, wh, side, cfg)
    assert torch.allclose(R_est, R, atol=1e-10)
    assert torch.allclose(t_est, t, atol=1e-9)


def test_mean_pose_averages_translations_and_rotations():
    R, t = _rotations(4, seed=5), _translations(4, seed=5)
    # k copies of a pose: that pose
    R_m, t_m = mean_pose(R[:, None].expand(4, 3, 3, 3), t[:, None].expand(4, 3, 3))
    assert torch.allclose(R_m, R, atol=1e-12)
    assert torch.allclose(t_m, t, atol=1e-12)
    # the pose turned by ±5° about one axis: the pose itself, proper; t the plain mean
    turn = torch.as_tensor(Rotation.from_rotvec([[0.0, 0.0, 0.0873]]).as_matrix(), dtype=D64)
    pair = torch.stack([R @ turn, R @ turn.transpose(1, 2)], dim=1)
    shift = torch.tensor([[[1.0, -2.0, 3.0]], [[-1.0, 2.0, 5.0]]], dtype=D64).transpose(0, 1)
    R_m, t_m = mean_pose(pair, t[:, None] + shift)
    assert torch.allclose(R_m, R, atol=1e-12)
    assert torch.allclose(torch.linalg.det(R_m), torch.ones(4, dtype=D64))
    assert torch.allclose(t_m, t + torch.tensor([0.0, 0.0, 4.0], dtype=D64), atol=1e-12)


def test_nearest_rotation_is_proper_and_keeps_rotations():
    R = _rotations(3, seed=6)
    assert torch.allclose(nearest_rotation(R + 1e-7), R, atol=1e-6)
    # a reflection's nearest proper rotation: flip the axis of its smallest singular value
    mirror = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=D64))[None] @ R
    near = nearest_rotation(mirror * torch.tensor([1.0, 2.0, 3.0], dtype=D64)[:, None])
    assert torch.allclose(torch.linalg.det(near), torch.ones(3, dtype=D64))
    assert torch.allclose(near @ near.transpose(1, 2), torch.eye(3, dtype=D64).expand(3, 3, 3))


# --- ROIs ----------------------------------------------------------------------------------------


def test_dzi_boxes_test_time_and_jitter():
    boxes = torch.tensor([[100.0, 50.0, 40.0, 20.0], [10.0, 10.0, 600.0, 300.0]])
    centre, side = dzi_boxes(boxes, None, (0.25, 0.25, 1.5), IMAGE_HW)
    assert torch.allclose(centre, torch.tensor([[120.0, 60.0], [310.0, 160.0]]))
    assert torch.allclose(side, torch.tensor([60.0, 640.0]))  # 900 clipped to max(H, W)

    cfg = PoseConfig()
    boxes = boxes[:1].expand(500, 4)
    c1, s1 = dzi_boxes(boxes, torch.Generator().manual_seed(0), cfg, IMAGE_HW)
    c2, s2 = dzi_boxes(boxes, torch.Generator().manual_seed(0), cfg, IMAGE_HW)
    assert torch.equal(c1, c2)
    assert torch.equal(s1, s2)
    assert ((s1 >= 60.0 * 0.75) & (s1 <= 60.0 * 1.25)).all()
    assert s1.std() > 5.0
    shift = (c1 - torch.tensor([120.0, 60.0])).abs() / torch.tensor([40.0, 20.0])
    assert (shift <= 0.25 + 1e-6).all()
    assert shift.max() > 0.2


def test_crop_matches_cv2_warp_affine():
    H, W, S = 48, 64, 16
    img = np.random.default_rng(0).random((H, W, 3), dtype=np.float32)
    # inside, across the border (zero padding on both sides), and zoomed out past the image
    centre = torch.tensor([[20.37, 30.11], [60.0, 5.0], [31.0, 23.5]])
    side = torch.tensor([23.3, 40.0, 72.0])
    images = torch.from_numpy(img).permute(2, 0, 1)[None].expand(3, 3, H, W)
    ours = crop(images, centre, side, S).permute(0, 2, 3, 1).numpy()
    for b in range(3):
        k = float(side[b]) / S  # dst → src: src = centre + (u − S/2)·side/S
        cx, cy = centre[b].tolist()
        M = np.array([[k, 0.0, cx - S / 2 * k], [0.0, k, cy - S / 2 * k]])
        ref = cv2.warpAffine(
            img, M, (S, S), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP, borderValue=0
        )
        np.testing.assert_allclose(ours[b], ref, atol=1e-4)


def test_crop_nearest_keeps_labels_and_follows_the_index():
    labels = torch.randint(0, 9, (2, 1, 48, 64))
    centre = torch.tensor([[20.0, 30.0], [40.0, 12.0], [20.0, 30.0]])
    side = torch.tensor([32.0, 16.0, 32.0])
    index = torch.tensor([1, 0, 0])
    out = crop(labels, centre, side, 8, mode="nearest", index=index)
    assert out.dtype == labels.dtype
    assert torch.equal(out, crop(labels[index], centre, side, 8, mode="nearest"))
    # integer steps land on pixel centres: ROI pixel (i, j) is image pixel (cy + (i−4)·4, ...)
    assert torch.equal(out[2, 0], labels[0, 0, 14:46:4, 4:36:4])


def test_roi_coord_2d_equals_cropping_the_coordinate_image():
    H, W, S = 48, 64, 8
    v, u = torch.meshgrid(torch.arange(H, dtype=D64), torch.arange(W, dtype=D64), indexing="ij")
    coord_img = torch.stack([(u + 0.5) / W, (v + 0.5) / H])[None].expand(2, 2, H, W)
    centre = torch.tensor([[30.0, 20.0], [17.3, 29.9]], dtype=D64)  # ROIs inside the image
    side = torch.tensor([20.0, 13.7], dtype=D64)
    expected = crop(coord_img, centre, side, S)
    assert torch.allclose(roi_coord_2d(centre, side, S, (H, W)), expected, atol=1e-12)


# --- dense targets -----------------------------------------------------------------------------


def test_farthest_point_sampling_is_deterministic_and_spread():
    pts = _arc(200)
    k = 8
    picks = farthest_point_sampling(pts, k)
    assert torch.equal(picks, farthest_point_sampling(pts, k))
    far = torch.argmax((pts - pts.mean(dim=0)).norm(dim=1))
    assert torch.equal(picks[0], pts[far])
    d = torch.cdist(picks, picks) + 1e9 * torch.eye(k, dtype=D64)
    even_spacing = 2 * 10.0 * np.sin(np.pi / (k - 1) / 2)  # chord between evenly spaced picks
    assert d.min() > 0.5 * even_spacing
    with pytest.raises(ValueError, match="k must be"):
        farthest_point_sampling(pts, 201)


def test_xyz_to_region_labels_nearest_centre_and_background():
    fps = torch.tensor([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]])
    xyz = torch.tensor([[[1.0, 1.0, 0.0], [9.0, 1.0, 0.0]], [[1.0, 8.0, 1.0], [9.0, 9.0, 9.0]]])
    mask = torch.tensor([[True, True], [True, False]])
    assert torch.equal(xyz_to_region(xyz, mask, fps), torch.tensor([[1, 2], [3, 0]]))


def test_xyz_from_depth_recovers_points_of_a_rendered_plane():
    H, W = 24, 32
    K = torch.tensor([[[200.0, 0.0, 16.0], [0.0, 210.0, 12.0], [0.0, 0.0, 1.0]]], dtype=D64)
    R = torch.as_tensor(Rotation.from_euler("xyz", [20, -15, 30], degrees=True).as_matrix())[None]
    t = torch.tensor([[5.0, -3.0, 150.0]], dtype=D64)
    # "render" the object plane z_obj = 0: intersect each pixel ray with it
    v, u = torch.meshgrid(torch.arange(H, dtype=D64), torch.arange(W, dtype=D64), indexing="ij")
    rays = torch.stack([u, v, torch.ones_like(u)], -1) @ torch.linalg.inv(K[0]).T
    n_c = R[0, :, 2]  # plane normal in the camera frame
    depth = ((n_c @ t[0]) / (rays @ n_c))[None]
    mask = torch.ones(1, H, W, dtype=torch.bool)
    mask[:, :, : W // 2] = False
    xyz = xyz_from_depth(depth, mask, K, R, t)
    fg = xyz[0][mask[0]]
    assert torch.allclose(fg[:, 2], torch.zeros_like(fg[:, 2]), atol=1e-9)  # on the plane
    proj = (fg @ R[0].T + t[0]) @ K[0].T  # back into the image at its own pixel
    uv = torch.stack([u, v], -1)[mask[0]]
    assert torch.allclose(proj[:, :2] / proj[:, 2:], uv, atol=1e-9)
    assert (xyz[0][~mask[0]] == 0).all()


def test_normaliser_round_trip_and_isotropy():
    pts = _arc(100) * torch.tensor([1.0, 1.0, 1.0], dtype=D64) + torch.tensor([3.0, -2.0, 7.0])
    pts[:, 2] += torch.linspace(-0.2, 0.2, 100, dtype=D64)  # thin in z
    norm = XyzNormaliser.from_vertices(pts)
    n = norm.normalise(pts)
    assert torch.allclose(norm.denormalise(n), pts, atol=1e-12)
    assert n.min() >= 0.0
    assert n.max() <= 1.0
    assert torch.allclose(n[:, 0].max() - n[:, 0].min(), torch.tensor(1.0, dtype=D64))
    # one scale for all axes: distances shrink by the same factor in every direction
    ratio = torch.pdist(n) / torch.pdist(pts)
    assert torch.allclose(ratio, torch.full_like(ratio, 1.0 / norm.scale))
    assert torch.allclose(n[:, 2].max() - n[:, 2].min(), torch.tensor(0.4 / norm.scale, dtype=D64))


# --- network, losses, PnP ---------------------------------------------------------------------


@pytest.mark.parametrize("norm", ["gn", "bn"])
def test_network_output_shapes(norm):
    cfg = PoseConfig.from_dict({**PoseConfig.preset("test").to_dict(), "norm": norm})
    net = GdrPoseNet(cfg)
    s = cfg.roi_out
    out = net(torch.rand(2, 3, cfg.roi_in, cfg.roi_in), torch.rand(2, 2, s, s))
    shapes = {k: tuple(v.shape) for k, v in out.items()}
    R1 = cfg.num_regions + 1
    assert shapes == {
        "mask": (2, 1, s, s),
        "xyz": (2, 3, s, s),
        "region": (2, R1, s, s),
        "rot6d": (2, 6),
        "site": (2, 3),
    }


def _synthetic_batch(cfg: PoseConfig, n: int, seed: int = 0) -> tuple:
    """n ROIs whose image shows their xyz target (so the maps are learnable), float32."""
    s, f32 = cfg.roi_out, torch.float32
    g = torch.Generator().manual_seed(seed)
    i, j = torch.meshgrid(torch.arange(s, dtype=f32), torch.arange(s, dtype=f32), indexing="ij")
    cy, cx = (s / 2 + 4 * (torch.rand(2, n, 1, 1, generator=g) - 0.5)).unbind(0)
    radius = s / 4 + 2 * torch.rand(n, 1, 1, generator=g)
    mask = (((i - cy) ** 2 + (j - cx) ** 2) < radius**2).to(f32)[:, None]
    xyz = torch.stack([j / s, i / s, 0.5 + 0.3 * torch.sin(i / 3 + j / 5)]).expand(n, 3, s, s)
    pts_fg = xyz.permute(0, 2, 3, 1)[mask[:, 0] > 0]
    fps = farthest_point_sampling(pts_fg, cfg.num_regions)
    region = xyz_to_region(xyz.permute(0, 2, 3, 1), mask[:, 0] > 0, fps)
    img = F.interpolate(xyz * mask, size=cfg.roi_in, mode="nearest")

    R, t, K = _rotations(n, seed, f32), _translations(n, seed, f32), _intrinsics(n, f32)
    p = (K @ t[:, :, None])[:, :, 0]
    centre = p[:, :2] / p[:, 2:] + 5.0
    wh = torch.tensor([40.0, 30.0]).expand(n, 2).clone()
    side = 1.5 * wh.max(dim=1).values
    target = {
        "mask_visib": mask,
        "xyz": xyz.clone(),
        "region": region,
        "R": R,
        "t": t,
        "site": site_encode(t, SiteRoi(K, centre, wh, side, s, cfg.z_unit_mm)),
        "K": K,
        "centre": centre,
        "wh": wh,
        "side": side,
    }
    coord2d = roi_coord_2d(centre, side, s, IMAGE_HW)
    return img, coord2d, target, _arc(200).to(f32)


def test_losses_are_finite_with_empty_mask_samples():
    torch.manual_seed(0)
    cfg = PoseConfig.preset("test")
    net = GdrPoseNet(cfg)
    img, coord2d, target, pts = _synthetic_batch(cfg, 3)
    target["mask_visib"][1] = 0.0
    target["wh"][1] = 0.0  # an empty ROI may come with a degenerate box
    target["side"][1] = 0.0
    target["site"][1] = float("nan")
    losses = gdr_losses(net(img, coord2d), target, pts, cfg)
    assert set(losses) == {"mask", "xyz", "region", "pm", "centroid", "z", "total"}
    assert all(torch.isfinite(v) for v in losses.values())
    losses["total"].backward()
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)

    target["mask_visib"].zero_()  # nothing visible at all: only the mask term remains
    losses = gdr_losses(net(img, coord2d), target, pts, cfg)
    assert all(torch.isfinite(v) for v in losses.values())
    for key in ("xyz", "region", "pm", "centroid", "z"):
        assert losses[key] == 0.0


def test_losses_decrease_in_a_few_adam_steps():
    torch.manual_seed(0)
    cfg = PoseConfig.preset("test")
    net = GdrPoseNet(cfg)
    img, coord2d, target, pts = _synthetic_batch(cfg, 4)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    history = []
    for _ in range(60):
        losses = gdr_losses(net(img, coord2d), target, pts, cfg)
        opt.zero_grad()
        losses["total"].backward()
        opt.step()
        history.append({k: v.item() for k, v in losses.items()})
    first, last = history[0], history[-1]
    assert last["total"] < 0.5 * first["total"], (first, last)
    for key in ("xyz", "z", "pm"):
        assert last[key] < first[key], (key, first, last)


def test_mask_probability_and_mask_losses():
    cfg = PoseConfig.preset("test")
    l1 = PoseConfig.from_dict({**cfg.to_dict(), "mask_loss": "l1"})
    raw = torch.tensor([-3.0, 0.0, 0.4, 2.0])
    assert torch.allclose(mask_probability(raw, cfg), torch.sigmoid(raw))
    assert torch.equal(mask_probability(raw, l1), torch.tensor([0.0, 0.0, 0.4, 1.0]))
    with pytest.raises(ValueError, match="mask_loss"):
        PoseConfig.from_dict({**cfg.to_dict(), "mask_loss": "dice"})

    img, coord2d, target, pts = _synthetic_batch(cfg, 2)
    del img, coord2d
    s = cfg.roi_out
    base = {
        "xyz": target["xyz"],
        "region": torch.zeros(2, cfg.num_regions + 1, s, s),
        "rot6d": rot6d_from_matrix(ego_to_allo(target["R"], target["t"])),
        "site": target["site"],
    }
    # BCE against the soft mask: a hand-worked value for constant logits and targets
    soft = torch.full((2, 1, s, s), 0.25)
    logit = torch.full((2, 1, s, s), 0.5)
    bce = gdr_losses({**base, "mask": logit}, {**target, "mask_soft": soft}, pts, cfg)["mask"]
    expected = -(0.25 * math.log(torch.sigmoid(torch.tensor(0.5)).item()))
    expected -= 0.75 * math.log(1 - torch.sigmoid(torch.tensor(0.5)).item())
    assert bce.item() == pytest.approx(expected, rel=1e-6)
    # the optimum of BCE is the soft target itself (logit(0.25)), not the 0/1 mask's median
    at_target = torch.full((2, 1, s, s), math.log(0.25 / 0.75))
    best = gdr_losses({**base, "mask": at_target}, {**target, "mask_soft": soft}, pts, cfg)
    assert best["mask"] < bce
    # L1 (GDR-Net's) on the raw output against the 0/1 mask
    m = target["mask_visib"]
    got = gdr_losses({**base, "mask": 0.25 * torch.ones_like(m)}, target, pts, l1)["mask"]
    assert got.item() == pytest.approx((0.25 - m).abs().mean().item(), rel=1e-6)


def test_symmetric_pm_loss_vanishes_for_a_symmetric_pose():
    cfg = PoseConfig.preset("test")
    img, coord2d, target, pts = _synthetic_batch(cfg, 2)
    del img, coord2d
    # the half-circle arc is symmetric under a 180° turn about its y axis
    sym = torch.as_tensor(
        Rotation.from_euler("y", 180, degrees=True).as_matrix(), dtype=torch.float32
    )
    R_sym = target["R"] @ sym
    t = target["t"]
    out = {
        "mask": target["mask_visib"],
        "xyz": target["xyz"],
        "region": torch.zeros(2, cfg.num_regions + 1, cfg.roi_out, cfg.roi_out),
        "rot6d": rot6d_from_matrix(ego_to_allo(R_sym, t)),
        "site": target["site"],
    }
    symmetric = PoseConfig.from_dict({**cfg.to_dict(), "symmetric": True})
    assert gdr_losses(out, target, pts, symmetric, sym[None])["pm"] < 1e-5
    assert gdr_losses(out, target, pts, cfg, sym[None])["pm"] > 0.1  # symmetry off
    with pytest.raises(ValueError, match="sym_rotations"):
        gdr_losses(out, target, pts, symmetric, None)


def test_pnp_recovers_the_pose_from_perfect_xyz_maps():
    cfg = PoseConfig.preset("test")  # 16×16 output maps
    H, W = IMAGE_HW
    K = _intrinsics(1)
    R = torch.as_tensor(Rotation.from_euler("xyz", [25, -10, 40], degrees=True).as_matrix())[None]
    t = torch.tensor([[10.0, -5.0, 200.0]], dtype=D64)
    # a curved surface in front of the camera, as a depth map, and its object-frame xyz
    v, u = torch.meshgrid(torch.arange(H, dtype=D64), torch.arange(W, dtype=D64), indexing="ij")
    depth = (200.0 + 5.0 * torch.sin(u / 15.0) + 1e-3 * (v - 250.0) ** 2)[None]
    xyz_img = xyz_from_depth(depth, torch.ones(1, H, W, dtype=torch.bool), K, R, t)
    # ROI grid on whole pixels (side/S = 4 px, integer centre): nearest sampling is exact
    centre = torch.tensor([[330.0, 250.0]], dtype=D64)
    side = torch.tensor([64.0], dtype=D64)
    xyz_roi = crop(xyz_img.permute(0, 3, 1, 2), centre, side, cfg.roi_out, mode="nearest")
    normaliser = XyzNormaliser.from_vertices(xyz_roi.flatten(2)[0].T)
    out = {
        "xyz": normaliser.normalise(xyz_roi.permute(0, 2, 3, 1)).permute(0, 3, 1, 2),
        "mask": torch.full((1, 1, cfg.roi_out, cfg.roi_out), 10.0, dtype=D64),  # logits
    }
    R_est, t_est, ok = pnp_ransac_from_output(out, K, centre, side, normaliser, cfg)
    assert ok.tolist() == [True]
    assert R_est.dtype == np.float64
    assert _rot_err_deg(R_est[0], R[0].numpy()) < 1e-3
    assert np.abs(t_est[0] - t[0].numpy()).max() < 1e-3

    out["mask"][:, :, 2:] = -10.0  # 2 rows × 16 = 32 points left
    out["mask"][:, :, :, 2:] = -10.0  # 2×2 = 4 points: too few
    assert pnp_ransac_from_output(out, K, centre, side, normaliser, cfg)[2].tolist() == [False]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_runs_on_cuda():
    dev = torch.device("cuda")
    cfg = PoseConfig.preset("test")
    net = GdrPoseNet(cfg).to(dev)
    img, coord2d, target, pts = _synthetic_batch(cfg, 2)
    target = {k: v.to(dev) for k, v in target.items()}
    out = net(img.to(dev), coord2d.to(dev))
    losses = gdr_losses(out, target, pts.to(dev), cfg)
    losses["total"].backward()
    assert losses["total"].device.type == "cuda"
    assert torch.isfinite(losses["total"])
    R, t = pose_from_output(out, target["K"], target["centre"], target["wh"], target["side"], cfg)
    assert R.device.type == "cuda"
    assert t.shape == (2, 3)
    centre, side = dzi_boxes(
        torch.tensor([[100.0, 50.0, 40.0, 20.0]], device=dev), None, cfg, IMAGE_HW
    )
    assert crop(torch.rand(1, 3, 480, 640, device=dev), centre, side, 16).device.type == "cuda"
    assert roi_coord_2d(centre, side, 16, IMAGE_HW).device.type == "cuda"
