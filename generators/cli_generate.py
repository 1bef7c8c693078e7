"""``bopsurg generate``: replay recorded bags from randomised viewpoints into a BOP dataset."""

from __future__ import annotations

import argparse
import logging
import math
import time
from typing import TYPE_CHECKING, Any

from bopsurg.cli.inputs import add_executor_args, key_value
from bopsurg.errors import InputError
from bopsurg.executors import make_executor
from bopsurg.geometry import intrinsics_from_fov

if TYPE_CHECKING:
    from bopsurg.generators.replay import GenerateSettings

log = logging.getLogger(__name__)

HELP = "replay bags from randomised endoscope viewpoints and lighting into a BOP dataset"

DESCRIPTION = """\
Replay each recording (rosbag) --replays times from randomised endoscope (ECM) viewpoints
and lighting in a headless render backend (PyBullet by default), and write a BOP dataset:

  DATASET/models/obj_000001.ply (+ models_info.json)   the needle (obj 1), built by code,
                                                        or your mesh (--object-model)
  DATASET/camera.json, DATASET/test_targets_bop19.json
  DATASET/SPLIT/SCENE/{rgb,depth,mask,mask_visib}/     one scene per (bag, replay)
  DATASET/SPLIT/SCENE/scene_camera.json, scene_gt.json, scene_gt_info.json
  DATASET/SPLIT/SCENE/bopsurg_scene.json                the drawn viewpoint, light and seed
                                                        (and --domain wide's draw)
  DATASET/SPLIT/bopsurg_generate.json                   settings, seed, bag (and object
                                                        model) checksums

Scene ids: bag i (0-based, in command-line order), replay r -> scene i*replays + r + 1.
A frame is written every --period seconds of the recording; frames whose needle
visib_fract is below --min-visib are dropped. Depth is uint16 with depth_scale 0.1 mm.
Rerun the same command after an interruption: it resumes, and the same seed gives
byte-identical files.

--object-model PLY renders and annotates your needle mesh (mm) in its own model frame:
models/obj_000001.ply is your mesh and every GT pose is its pose. Its arc (centre, normal,
radius, extent; the tip is the end that tapers) is fitted and laid onto the recorded needle's
arc (centres, planes and arc middles coincide), so the replayed motion, grasps and driving
along the arc stay the recorded ones (the recorded needle: the one --needle-* describe, else
the one the bags were recorded for: 'bopsurg record --object-model PLY' plans the episode for
your needle, so the grasps hold its wire). One log line gives the fitted arc. A radius more
than 5 % off the recorded one is kept (your mesh defines the geometry): it is rendered at its
own size on the recorded arc's centre, with a warning; more than 5x off is taken for a mesh not in
mm and refused, like meshes that are not needles (one line, nothing written). The mesh's path
and sha256 are recorded in bopsurg_generate.json: resuming with another mesh is refused.

Recordings of real robots (any bag without bopsurg's /bopsurg/meta under the crtk map): any
of PSM1-3 (dVRK topics /PSM2/measured_js, ...), jaws and ECM optional, no needle topic. The
recorded arms are posed with the dVRK's own kinematics (--psm-tool), the needle is held in
one arm's jaws (--needle-holder) and the endoscope viewpoints are framed on the recorded
tool-tip workspace. 'bopsurg inspect BAG' shows what will be done.

Render backends are plugins (entry-point group 'bopsurg.render_backends'); --backend picks
one and each --backend-option KEY=VALUE goes to it. PyBullet's options: renderer=tiny|egl
(also --renderer), texture_seed=INT (procedural textures), light_distance=M (shadow light).
"""

EPILOG = """\
examples:
  bopsurg generate bags/ep001.bag --out data/needle --replays 4
  bopsurg generate bags/*.bag --out data/train --split train --workers 2 --annotate-instruments
  bopsurg generate bags/ep001.bag --out data/tex3 --backend-option texture_seed=3
  bopsurg generate bags/ep001.bag --out data/mine --object-model Needle.ply
  bopsurg generate bags/*.bag --out data/wide --split train --domain wide
  bopsurg generate pitch_exp_traj_01.bag --out data/dvrk --replays 4 --needle-holder psm2
"""


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add the subcommand."""
    from bopsurg.generators.replay import GenerateSettings

    d = GenerateSettings()
    p = sub.add_parser(
        "generate",
        help=HELP,
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("bags", nargs="+", metavar="BAG", help="recordings (ROS1 .bag or ROS2 folder)")
    p.add_argument("--out", required=True, metavar="DATASET", help="dataset root (created)")
    p.add_argument("--split", default="test", help="split folder (default: test)")
    p.add_argument("--replays", type=int, default=d.replays, help="replays per bag (default: 20)")
    p.add_argument(
        "--period", type=float, default=d.period, help="seconds between frames (default: 0.5)"
    )
    p.add_argument("--seed", type=int, default=d.seed, help="dataset seed (default: 0)")
    p.add_argument(
        "--min-visib",
        type=float,
        default=d.min_visib,
        help="drop frames whose needle visib_fract is below this (default: 0.1)",
    )
    p.add_argument(
        "--delta", type=float, default=d.delta_mm, help="visibility tolerance, mm (default: 1)"
    )
    p.add_argument("--topic-map", default=d.topic_map, help="topic map: crtk, ambf or a TOML file")
    add_recording_args(p)
    _add_camera_args(p, d)
    _add_needle_args(p)
    p.add_argument(
        "--object-model",
        default=None,
        metavar="PLY",
        help="your needle mesh (PLY, mm) to render and annotate as obj 1, in its own model "
        "frame (see above)",
    )
    p.add_argument(
        "--rgb-format", choices=("png", "jpg"), default=d.rgb_format, help="rgb file format"
    )
    p.add_argument("--stereo", action="store_true", help="also render the right camera")
    p.add_argument(
        "--annotate-instruments",
        action="store_true",
        help="annotate instrument parts as further objects (obj_id 2, 3, ...)",
    )
    p.add_argument(
        "--domain",
        choices=("paper", "wide"),
        default=d.domain,
        help="randomisation profile (default: paper): 'paper' draws the ECM viewpoint and "
        "light only, as the paper's replays; 'wide' also draws a camera-to-needle distance of "
        "20-120 mm (on half the replays with the endoscope orbiting the needle: any side, "
        "10-70 deg above the tissue, any roll), a light set-up, phantom surface and colour, "
        "background, a specular "
        "needle, grey/black materials on Large-Needle-Driver-like instruments and a simulated "
        "suture thread from the needle's tail (an occluder in the needle's masks), and on "
        "half the replays suture targets painted beside the cuts, and on half a pad with "
        "one groove its whole length instead of three incisions; every draw is "
        "recorded in bopsurg_scene.json",
    )
    _add_backend_args(p, d)
    add_executor_args(p, unit="replay")
    p.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    p.set_defaults(func=run)


def add_recording_args(p: argparse.ArgumentParser) -> None:
    """``--joints --psm-tool --needle-holder`` (recordings of real robots; also ``inspect``)."""
    from bopsurg.generators.dvrk_tools import DEFAULT_TOOL

    p.add_argument(
        "--joints",
        choices=("measured", "setpoint"),
        default=None,
        help="read the PSM joints (and jaws, Cartesian poses) from the measured_js or the "
        "setpoint_js topics (default: the first the topic map finds, measured first)",
    )
    p.add_argument(
        "--psm-tool",
        default=None,
        metavar="NAME",
        help="real robots' recordings: the dVRK tool whose kinematics (sawIntuitiveResearchKit "
        f"share/tool/NAME.json) pose the arms (default: {DEFAULT_TOOL})",
    )
    p.add_argument(
        "--needle-holder",
        default="auto",
        metavar="ARM",
        help="real robots' recordings (no needle topic): the arm whose jaws hold the needle, "
        "psm1|psm2|psm3, 'auto' (the recorded arm, or the first of several) or 'none' "
        "(on the tissue) (default: auto)",
    )


def _add_camera_args(p: argparse.ArgumentParser, d: GenerateSettings) -> None:
    """``--width --height --fov --K``."""
    p.add_argument("--width", type=int, default=d.width, help="image width, px (default: 640)")
    p.add_argument("--height", type=int, default=d.height, help="image height, px (default: 480)")
    p.add_argument(
        "--fov",
        type=float,
        default=1.2,
        help="vertical field of view, rad (default: 1.2, the simulator's endoscope); "
        "K = [[f, 0, W/2], [0, f, H/2], [0, 0, 1]] with f = H / (2 tan(fov/2))",
    )
    p.add_argument(
        "--K",
        default=None,
        metavar="FX,FY,CX,CY",
        help="explicit intrinsics in px (overrides --fov)",
    )


def _add_needle_args(p: argparse.ArgumentParser) -> None:
    """``--needle-arc --needle-radius --needle-wire``."""
    p.add_argument(
        "--needle-arc",
        type=float,
        default=None,
        metavar="DEG",
        help="needle arc incl. the tapered tip, degrees (default: 128.5; 135 = 3/8 circle, "
        "180 = 1/2 circle)",
    )
    p.add_argument(
        "--needle-radius", type=float, default=None, metavar="MM", help="centre-line radius, mm"
    )
    p.add_argument(
        "--needle-wire", type=float, default=None, metavar="MM", help="wire diameter, mm"
    )


def _add_backend_args(p: argparse.ArgumentParser, d: GenerateSettings) -> None:
    """``--backend --backend-option --renderer --amodal-renderer``."""
    p.add_argument(
        "--renderer",
        choices=("tiny", "egl"),
        default=None,
        help="PyBullet renderer, short for --backend-option renderer=... (default: tiny)",
    )
    p.add_argument("--backend", default=d.backend, help="render backend plugin (default: pybullet)")
    p.add_argument(
        "--amodal-renderer",
        default=d.renderer,
        metavar="NAME",
        help="depth renderer plugin for each object alone on the 3x canvas, the one 'bopsurg "
        "annotate' uses (default: pybullet), or 'backend' for the render backend's own",
    )
    p.add_argument(
        "--backend-option",
        type=key_value,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="option of the render backend (repeatable; see above for PyBullet's)",
    )


def _intrinsics(args: argparse.Namespace) -> tuple[tuple[float, float, float], ...]:
    if args.width < 1 or args.height < 1:
        raise InputError("must be >= 1 px", field="--width/--height")
    if args.K:
        try:
            fx, fy, cx, cy = (float(v) for v in args.K.split(","))
        except ValueError:
            raise InputError("expected four numbers FX,FY,CX,CY", field="--K") from None
        if fx <= 0 or fy <= 0:
            raise InputError("focal lengths must be > 0", field="--K")
    else:
        if not 0 < args.fov < math.pi:
            raise InputError("must be in (0, pi) rad", field="--fov")
        return tuple(
            tuple(r) for r in intrinsics_from_fov(args.width, args.height, args.fov).tolist()
        )
    return ((fx, 0.0, cx), (0.0, fy, cy), (0.0, 0.0, 1.0))


def _needle_config(args: argparse.Namespace) -> dict[str, float]:
    from bopsurg.needle import NeedleSpec

    cfg: dict[str, float] = {}
    if args.needle_arc is not None:
        tip = NeedleSpec.tip_deg
        if not tip < args.needle_arc <= 360:
            raise InputError(f"must be in ({tip}, 360] degrees", field="--needle-arc")
        cfg["body_deg"] = args.needle_arc - tip
    if args.needle_radius is not None:
        if args.needle_radius <= 0:
            raise InputError("must be > 0", field="--needle-radius")
        cfg["arc_radius"] = args.needle_radius
    if args.needle_wire is not None:
        if args.needle_wire <= 0:
            raise InputError("must be > 0", field="--needle-wire")
        cfg["wire_diameter"] = args.needle_wire
    return cfg


def _backend_config(args: argparse.Namespace) -> dict[str, Any]:
    """The scene keys of the flags plus the --backend-option pairs (recorded as given)."""
    from bopsurg.generators.backend import SCENE_KEYS

    options = dict(args.backend_option)
    for key in options:
        if key in SCENE_KEYS:
            raise InputError(
                f"{key!r} describes the scene, not the backend; use --annotate-instruments, "
                "--needle-* or --object-model",
                field="--backend-option",
            )
    if args.renderer is not None:
        options["renderer"] = args.renderer
    elif args.backend == "pybullet":
        options.setdefault("renderer", "tiny")  # recorded explicitly, as it always was
    config: dict[str, Any] = {"annotate_instruments": bool(args.annotate_instruments)}
    needle = _needle_config(args)
    if needle:
        config["needle"] = needle
    if args.object_model is not None:  # resolved to {path, sha256} by generate_dataset
        config["object_model"] = args.object_model
    return {**config, **options}


def run(args: argparse.Namespace) -> int:
    """Generate the dataset and report what was written."""
    from bopsurg.generators.generate import generate_dataset
    from bopsurg.generators.replay import GenerateSettings

    if args.period <= 0:
        raise InputError("must be > 0", field="--period")
    settings = GenerateSettings(
        replays=args.replays,
        period=args.period,
        seed=args.seed,
        min_visib=args.min_visib,
        delta_mm=args.delta,
        stereo=args.stereo,
        topic_map=args.topic_map,
        backend=args.backend,
        backend_config=_backend_config(args),
        renderer=None if args.amodal_renderer == "backend" else args.amodal_renderer,
        width=args.width,
        height=args.height,
        K=_intrinsics(args),
        rgb_format=args.rgb_format,
        domain=args.domain,
        needle_holder=args.needle_holder,
        psm_tool=args.psm_tool,
        joint_source=args.joints,
    )
    t0 = time.perf_counter()
    report = generate_dataset(
        args.bags,
        args.out,
        split=args.split,
        settings=settings,
        workers=args.workers,
        executor=make_executor(args.executor, workers=args.workers, ray_address=args.ray_address),
        progress=not args.no_progress,
    )
    dt = time.perf_counter() - t0
    rate = report.frames_rendered / dt if dt > 0 else 0.0
    print(
        f"{args.out}: {report.scenes} scenes ({report.scenes_skipped} already done), "
        f"{report.frames_written} frames written of {report.frames_rendered} rendered "
        f"in {dt:.1f} s ({rate:.1f} frames/s)"
    )
    return 0
