"""Bench: render-only speed of the PyBullet backend and depth renderer at 640×480.

Scene content is realistic: the suturing pad and drape fill the view, both instruments are in
view (wrists bent, jaws open or closed), the needle lies on the pad; the endoscope (ECM)
moves randomly around its rest pose (seeded). For each renderer (TinyRenderer, and EGL if the
plugin loads) it times, per frame:

- ``set_state``: forward kinematics and pose updates of all parts;
- ``render``: the whole scene (RGB + depth + instance map, incl. numpy post-processing);
- ``alone 1x`` / ``alone 3x``: ``render_object_depth`` of the needle on the image and on
  BOP's 3× canvas, and of every instrument part (3×) with ``annotate_instruments``;

and the :class:`~bopsurg.generators.depth_renderer.PyBulletDepthRenderer` plugin (VSD) on the
needle. Times are medians over the frames; fps = 1000 / median ms. The last line estimates
how many annotated frames (render + needle 3× render) two such processes would produce in 10
minutes, rendering only.

    python bench/bench_render.py [--frames 40] [--no-egl] [--instruments]
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from collections.abc import Callable

import numpy as np

from bopsurg.generators.backend import CameraSpec, LightSpec, SceneSpec, SceneState
from bopsurg.generators.depth_renderer import PyBulletDepthRenderer
from bopsurg.generators.kinematics import ecm_camera_pose, pose, rot_z
from bopsurg.generators.pybullet_backend import PyBulletBackend

K = np.array([[350.807, 0.0, 320.0], [0.0, 350.807, 240.0], [0.0, 0.0, 1.0]])
W, H = 640, 480
K3 = K.copy()
K3[:2, 2] += (W, H)
JOINTS = {
    "psm1": np.array([0.10, -0.05, 0.120, 0.3, 0.2, -0.2]),
    "psm2": np.array([-0.10, 0.05, 0.125, -0.2, -0.3, 0.25]),
}


def frames(n: int, seed: int = 0) -> list[tuple[SceneState, CameraSpec, LightSpec]]:
    """Seeded random scene states and endoscope viewpoints."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        joints = {
            k: v + rng.normal(0.0, [0.03, 0.03, 0.003, 0.2, 0.2, 0.2]) for k, v in JOINTS.items()
        }
        jaws = {k: float(rng.uniform(0.0, 0.8)) for k in JOINTS}
        needle = pose(
            rot_z(rng.uniform(-np.pi, np.pi)),
            [rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01), 0.003],
        )
        ecm = np.array(
            [
                rng.uniform(-0.25, 0.25),
                rng.uniform(-0.2, 0.2),
                rng.uniform(-0.02, 0.02),
                rng.uniform(-0.5, 0.5),
            ]
        )
        state = SceneState(psm_joints=joints, jaws=jaws, ecm_joints=ecm, needle_pose=needle)
        cam = CameraSpec(K=K, width=W, height=H, T_world_cam=ecm_camera_pose(ecm))
        light = LightSpec(
            direction=np.array([rng.uniform(-0.5, 0.5), -0.5, 1.0]),
            ambient=float(rng.uniform(0.4, 0.7)),
        )
        out.append((state, cam, light))
    return out


def median_ms(times: list[float]) -> float:
    return 1e3 * float(np.median(times))


def timed(fn: Callable[[], object]) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def bench_backend(renderer: str, data: list, instruments: bool) -> dict[str, float] | None:
    backend = PyBulletBackend({"renderer": renderer})
    t0 = time.perf_counter()
    try:
        backend.load_scene(SceneSpec(annotate_instruments=instruments))
    except RuntimeError as err:
        print(f"{renderer}: not available ({err})")
        return None
    load_s = time.perf_counter() - t0
    names = [n for n, _ in backend.annotated_objects()]
    rows: dict[str, list[float]] = {
        "set_state": [],
        "render": [],
        "needle alone 1x": [],
        "needle alone 3x": [],
    }
    if instruments:
        rows["6 tool parts alone 3x"] = []
    visible = []
    backend.set_state(data[0][0])
    backend.render(data[0][1], data[0][2])  # warm-up
    for state, cam, light in data:
        cam3 = CameraSpec(K=K3, width=3 * W, height=3 * H, T_world_cam=cam.T_world_cam)
        rows["set_state"].append(timed(lambda s=state: backend.set_state(s)))
        t = time.perf_counter()
        frame = backend.render(cam, light)
        rows["render"].append(time.perf_counter() - t)
        visible.append(int((frame.instance == 1).sum()))
        rows["needle alone 1x"].append(
            timed(lambda c=cam: backend.render_object_depth("needle", c))
        )
        rows["needle alone 3x"].append(
            timed(lambda c=cam3: backend.render_object_depth("needle", c))
        )
        if instruments:
            rows["6 tool parts alone 3x"].append(
                timed(lambda c=cam3: [backend.render_object_depth(n, c) for n in names[1:]])
            )
    backend.close()
    seen = np.mean(np.array(visible) > 0)
    print(
        f"\n{renderer}: load_scene {load_s:.2f} s; needle visible in {seen:.0%} of frames, "
        f"median {np.median(visible):.0f} px"
    )
    print(f"  {'step':<24}{'median ms':>10}{'fps':>8}")
    result = {}
    for name, times in rows.items():
        ms = median_ms(times)
        result[name] = ms
        print(f"  {name:<24}{ms:>10.1f}{1e3 / ms:>8.1f}")
    return result


def bench_depth_renderer(data: list) -> None:
    from bopsurg.needle import needle_mesh

    model = needle_mesh()
    renderer = PyBulletDepthRenderer()
    t0 = time.perf_counter()
    renderer.render_depth(model, np.eye(3), np.array([0.0, 0.0, 60.0]), K, W, H)
    first_s = time.perf_counter() - t0
    rows: dict[str, list[float]] = {"needle 640x480": [], "needle 3x canvas": []}
    for state, cam, _ in data:
        T = np.linalg.inv(cam.T_world_cam) @ state.needle_pose
        R, t = T[:3, :3], 1e3 * T[:3, 3]
        rows["needle 640x480"].append(
            timed(lambda R=R, t=t: renderer.render_depth(model, R, t, K, W, H))
        )
        rows["needle 3x canvas"].append(
            timed(lambda R=R, t=t: renderer.render_depth(model, R, t, K3, 3 * W, 3 * H))
        )
    renderer.close()
    print(f"\nPyBulletDepthRenderer (VSD plugin): first call incl. upload {1e3 * first_s:.0f} ms")
    print(f"  {'step':<24}{'median ms':>10}{'fps':>8}")
    for name, times in rows.items():
        ms = median_ms(times)
        print(f"  {name:<24}{ms:>10.1f}{1e3 / ms:>8.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--no-egl", action="store_true", help="skip the EGL plugin")
    parser.add_argument("--instruments", action="store_true", help="also annotate the tool parts")
    args = parser.parse_args()
    print(
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
        f"load average {os.getloadavg()[0]:.2f}; {args.frames} frames at {W}x{H}"
    )
    data = frames(args.frames)
    results = {}
    for renderer in ("tiny",) if args.no_egl else ("tiny", "egl"):
        res = bench_backend(renderer, data, args.instruments)
        if res is not None:
            results[renderer] = res
    bench_depth_renderer(data)
    print()
    for renderer, res in results.items():
        per_frame = res["set_state"] + res["render"] + res["needle alone 3x"]
        print(
            f"{renderer}: {per_frame:.1f} ms per annotated frame (render + needle 3x) -> "
            f"~{2 * 600e3 / per_frame:,.0f} frames in 10 min on 2 processes (rendering only)"
        )


if __name__ == "__main__":
    main()
