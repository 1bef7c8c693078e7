"""Recordings of a real dVRK: the dVRK's kinematics, reading, the fk-check, staging, generate."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bopsurg.bop.check import check_dataset
from bopsurg.bop.dataset import BopDataset
from bopsurg.cli.main import main
from bopsurg.errors import InputError
from bopsurg.generators.bags import BagError, read_bag
from bopsurg.generators.dvrk_tools import TOOL_NAMES, dvrk_psm
from bopsurg.generators.fk_check import fk_check, pair_by_stamp, register_rigid
from bopsurg.generators.kinematics import SIMULATOR_PSM, mdh, psm_link_frames
from bopsurg.generators.staging import CLEARANCE, GRASP, GRASP_JAW, stage_recording
from bopsurg.needle import NeedleSpec
from tests.generators.dvrk_fixture import known_registration, write_dvrk_bag

# ------------------------------------------------------------------ the dVRK's kinematics


def test_dvrk_chain_is_the_modified_dh_of_the_files_by_hand():
    """At zero angles the shaft is the base's −z: the tip sits at insertion − 0.4318 + D + A
    below the RCM, with the tool-tip rotation of tooltip_offset (x → −y... by hand)."""
    kin = dvrk_psm("LARGE_NEEDLE_DRIVER_400006")
    q = np.array([0.0, 0.0, 0.12, 0.0, 0.0, 0.0])
    T = kin.link_frames(q)[-1]
    assert T[2, 3] == pytest.approx(-(0.12 - 0.4318 + 0.4162 + 0.0091), abs=1e-6)
    assert np.abs(T[:2, 3]).max() < 1e-6
    # Tip axes: z along the shaft (down), x and y across it; 1.5708 is not quite pi/2
    np.testing.assert_allclose(T[:3, :3], [[0, 1, 0], [1, 0, 0], [0, 0, -1]], atol=1e-4)
    # One link by hand: Rx(alpha) Tx(a) Rz(theta) Tz(d)
    ca, sa, ct, st = np.cos(0.3), np.sin(0.3), np.cos(0.7), np.sin(0.7)
    by_hand = np.array(
        [
            [ct, -st, 0, 0.01],
            [st * ca, ct * ca, -sa, -sa * 0.2],
            [st * sa, ct * sa, ca, ca * 0.2],
            [0, 0, 0, 1],
        ]
    )
    np.testing.assert_allclose(mdh(0.3, 0.01, 0.7, 0.2), by_hand, atol=1e-15)


def test_outer_yaw_and_pitch_swing_the_tip_about_the_rcm():
    kin = dvrk_psm()
    q = np.array([0.0, 0.0, 0.15, 0.0, 0.0, 0.0])
    reach = np.linalg.norm(kin.link_frames(q)[-1][:3, 3])
    for q0, q1 in ((0.4, 0.0), (0.0, -0.3), (0.2, 0.25)):
        tip = kin.link_frames([q0, q1, 0.15, 0.0, 0.0, 0.0])[-1][:3, 3]
        assert np.linalg.norm(tip) == pytest.approx(reach, abs=1e-9)
    # outer yaw turns about the base's y axis (dVRK: positive yaw moves the tip to +x... or -x)
    tip = kin.link_frames([0.3, 0.0, 0.15, 0.0, 0.0, 0.0])[-1][:3, 3]
    assert abs(tip[1]) < 1e-5
    assert abs(tip[0]) > 0.01


def test_simulator_kinematics_unchanged_and_batched_fk_matches():
    rng = np.random.default_rng(3)
    q = rng.uniform(-0.6, 0.6, (20, 6))
    q[:, 2] = rng.uniform(0.05, 0.2, 20)
    for kin in (SIMULATOR_PSM, dvrk_psm(), dvrk_psm("mega_needle_driver_400194")):
        batch = kin.tip_poses(q)
        for i in range(len(q)):
            np.testing.assert_allclose(batch[i], kin.link_frames(q[i])[-1], atol=1e-14)
    # The simulator's chain through PsmKinematics is the historic one, bit for bit.
    for qi in q[:5]:
        old = psm_link_frames(qi)
        new = SIMULATOR_PSM.link_frames(qi)
        assert all(np.array_equal(a, b) for a, b in zip(old, new, strict=True))


def test_tools_cite_their_source_and_unknown_tools_are_refused():
    kin = dvrk_psm()
    assert "jhu-dvrk/sawIntuitiveResearchKit@9e535e68eb7ff276d0516142bde82474fe9dc4bf" in kin.source
    assert "share/tool/LARGE_NEEDLE_DRIVER_400006.json" in kin.source
    assert len(TOOL_NAMES) >= 2
    assert dvrk_psm("large_needle_driver_420006").joints[3].d == 0.467
    with pytest.raises(InputError, match="unknown dVRK tool"):
        dvrk_psm("LASER_SWORD_1")


# ------------------------------------------------------------------ registration


def test_register_rigid_recovers_a_known_transform():
    rng = np.random.default_rng(1)
    P = rng.normal(size=(30, 3))
    T = known_registration()
    R, t = register_rigid(P, P @ T[:3, :3].T + T[:3, 3])
    np.testing.assert_allclose(R, T[:3, :3], atol=1e-12)
    np.testing.assert_allclose(t, T[:3, 3], atol=1e-12)


def test_pair_by_stamp_pairs_nearest_within_tolerance():
    a = np.array([0.0, 0.01, 0.02, 0.05])
    b = np.array([0.0002, 0.0199, 0.03])
    ia, ib = pair_by_stamp(a, b, tolerance=5e-4)
    assert ia.tolist() == [0, 2]
    assert ib.tolist() == [0, 1]


# ------------------------------------------------------------------ real bags


@pytest.fixture(params=["ros1", "ros2", "mcap"])
def dvrk_bag(request, tmp_path):
    path = tmp_path / ("PSM2_run.bag" if request.param == "ros1" else "PSM2_run")
    joints = write_dvrk_bag(path, request.param, duration=1.0)
    return path, joints["psm2"]


def test_real_layout_reads_one_arm_with_cartesian_poses(dvrk_bag):
    path, q = dvrk_bag
    rec = read_bag(path)
    assert rec.robot == "dvrk"
    assert sorted(rec.psm_joints) == ["psm2"]
    assert sorted(rec.psm_poses) == ["psm2"]
    assert rec.jaws == {}
    assert rec.ecm_joints is None
    assert rec.needle_pose is None
    np.testing.assert_array_equal(rec.psm_joints["psm2"][1], q)
    setpoint = read_bag(path, joint_source="setpoint")
    np.testing.assert_array_equal(setpoint.psm_joints["psm2"][1][1:], q[:-1])


def test_fk_check_finds_the_known_registration(dvrk_bag):
    path, _ = dvrk_bag
    rec = read_bag(path)
    check = fk_check("psm2", rec.psm_joints["psm2"], rec.psm_poses["psm2"], dvrk_psm())
    assert check is not None
    assert check.pairs == 101
    T = known_registration()
    assert np.abs(check.T_frame_base[:3, 3] - T[:3, 3]).max() < 1e-6  # m
    np.testing.assert_allclose(check.T_frame_base[:3, :3], T[:3, :3], atol=1e-6)
    assert check.max_mm < 1e-3
    assert check.rot_max_deg < 1e-4
    # the simulator's lengths are not the robot's: millimetres off after the best registration
    sim = fk_check("psm2", rec.psm_joints["psm2"], rec.psm_poses["psm2"], SIMULATOR_PSM)
    assert sim is not None
    assert sim.rms_mm > 0.2


def test_inspect_prints_streams_plan_and_fk_check(tmp_path, capsys):
    path = tmp_path / "run.bag"
    write_dvrk_bag(path, "ros1", duration=1.0, cp_noise_m=2e-5)
    assert main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert "/PSM2/measured_cp  geometry_msgs/msg/PoseStamped  101 msgs  100.0 Hz  frame ECM" in out
    assert "psm2: joints /PSM2/measured_js, Cartesian /PSM2/measured_cp, jaw none" in out
    assert "needle: none" in out
    assert "held in psm2's jaws" in out
    line = next(x for x in out.splitlines() if x.startswith("fk-check PSM2: 101 pairs, rms "))
    rms = float(line.split("rms ")[1].split(" mm")[0])
    assert 0.0 < rms <= 0.1


def test_inspect_names_an_arm_recorded_without_joints(tmp_path, capsys):
    path = tmp_path / "mixed.bag"
    write_dvrk_bag(path, "ros1", duration=0.2, arms=("psm1", "psm2"), cartesian_only=("psm1",))
    assert main(["inspect", str(path)]) == 0
    out = capsys.readouterr().out
    assert "psm1: joints none, Cartesian /PSM1/measured_cp, jaw none (not rendered" in out
    assert "render the recorded arms psm2 " in out
    assert "fk-check PSM2: 21 pairs" in out
    assert "fk-check PSM1" not in out


def test_a_bag_without_arms_is_one_clear_line(tmp_path):
    path = tmp_path / "none.bag"
    write_dvrk_bag(path, "ros1", duration=0.1, arms=())
    with pytest.raises(BagError, match="required topic missing") as err:
        read_bag(path)
    assert "/PSM2/measured_js" in str(err.value)
    assert "\n" not in str(err.value)


# ------------------------------------------------------------------ staging


def test_staging_holds_the_needle_in_the_recorded_arms_jaws(tmp_path):
    path = tmp_path / "run.bag"
    write_dvrk_bag(path, "ros1", duration=1.0)
    rec = read_bag(path)
    staged, how = stage_recording(rec, dvrk_psm())
    layout = staged.layout
    assert layout is not None
    assert layout.arms == ("psm2",)
    assert how.holder == "psm2"
    assert layout.kinematics.name == "LARGE_NEEDLE_DRIVER_400006"
    needle = NeedleSpec()
    for t in (0.0, 0.37, 1.0):
        state = staged.state_at(t)
        assert set(state.psm_joints) == {"psm2"}
        assert state.jaws == {"psm2": GRASP_JAW}
        tip = layout.arm_base("psm2") @ layout.kinematics.link_frames(state.psm_joints["psm2"])[-1]
        # the wire's grasp point lies GRASP depth in front of the jaw pivot, along the jaws
        s = np.deg2rad(GRASP[0])
        r = needle.arc_radius * 1e-3
        grasped = state.needle_pose @ np.array([r * np.cos(s), r * np.sin(s), 0.0, 1.0])
        want = tip[:3, 3] + GRASP[2] * 1e-3 * tip[:3, 2]
        np.testing.assert_allclose(grasped[:3], want, atol=1e-9)
        assert grasped[2] >= CLEARANCE - 1e-9  # above the tissue
    # the view target is the workspace centre, in front of the endoscope's base pose
    forward = layout.ecm_base()[:3, 2]
    to_target = np.asarray(layout.view_target) - np.asarray(layout.ecm_frame_origin)
    assert np.dot(forward, to_target) == pytest.approx(np.linalg.norm(to_target))


def test_staging_of_several_arms_and_holders(tmp_path):
    path = tmp_path / "two.bag"
    write_dvrk_bag(path, "ros1", duration=0.5, arms=("psm3", "psm1"), jaw=True)
    rec = read_bag(path)
    staged, how = stage_recording(rec, dvrk_psm())
    assert staged.layout is not None
    assert staged.layout.arms == ("psm1", "psm3")
    assert how.holder == "psm1"
    assert staged.jaws["psm3"][1][0] == pytest.approx(0.4)
    staged, how = stage_recording(rec, dvrk_psm(), needle_holder="PSM3")
    assert how.holder == "psm3"
    assert staged.jaws["psm1"][1][0] == pytest.approx(0.4)
    staged, how = stage_recording(rec, dvrk_psm(), needle_holder="none")
    assert how.holder is None
    lying = staged.state_at(0.2).needle_pose
    assert lying[2, 3] == pytest.approx(0.36e-3)
    assert lying[2, 2] == pytest.approx(1.0)
    with pytest.raises(InputError, match="not a recorded arm"):
        stage_recording(rec, dvrk_psm(), needle_holder="psm2")


# ------------------------------------------------------------------ generate


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_generate_a_real_one_arm_recording(tmp_path, fmt):
    path = tmp_path / ("PSM2_run.bag" if fmt == "ros1" else "PSM2_run")
    write_dvrk_bag(path, fmt, duration=2.0)
    out = tmp_path / "ds"
    args = ["generate", str(path), "--out", str(out), "--replays", "1", "--period", "1"]
    args += ["--width", "160", "--height", "120", "--no-progress"]
    assert main(args) == 0
    assert check_dataset(out, "test") == []
    scene = BopDataset(out, "test").scene(1)
    assert scene.im_ids == [0, 1, 2]  # the needle is in view in every frame
    record = json.loads((out / "test" / "bopsurg_generate.json").read_text())
    assert "needle_holder" not in record["settings"]  # defaults are not recorded
    # the annotated needle is where the staged recording holds it
    from bopsurg.generators.generate import load_recording
    from bopsurg.generators.replay import GenerateSettings

    staged = load_recording(str(path), GenerateSettings())
    cam = scene.camera[1]
    T_cam_world = np.eye(4)
    T_cam_world[:3, :3], T_cam_world[:3, 3] = cam.R_w2c, cam.t_w2c * 1e-3
    T = T_cam_world @ staged.state_at(1.0).needle_pose
    gt = scene.gt[1][0]
    np.testing.assert_allclose(gt.R, T[:3, :3], atol=1e-6)
    np.testing.assert_allclose(gt.t, T[:3, 3] * 1e3, atol=1e-3)


def test_generate_refuses_a_tool_for_a_simulator_recording(tmp_path):
    from bopsurg.generators.bags import write_bag
    from bopsurg.generators.trajectory import synthesize_suturing

    path = tmp_path / "sim.bag"
    write_bag(path, synthesize_suturing(1, duration=1.0, rate_hz=10.0))
    args = ["generate", str(path), "--out", str(tmp_path / "ds"), "--replays", "1"]
    assert main([*args, "--psm-tool", "LARGE_NEEDLE_DRIVER_400006"]) != 0


def test_real_joints_may_overshoot_their_limits_a_little(tmp_path):
    joints = np.array([[0.0, 0.0, -0.01, 0.0, 0.0, 0.0], [0.0, 0.0, 0.1, 0.0, 0.0, 0.0]])
    for k, (q, ok) in enumerate(((joints, True), (joints - [0, 0, 0.1, 0, 0, 0], False))):
        path = tmp_path / f"limits{k}.bag"
        write_dvrk_bag(path, "ros1", duration=0.01, joints=q)
        if ok:  # 1 cm below the insertion's lower limit: a real arm's overshoot
            assert read_bag(path).psm_joints["psm2"][1][0, 2] == pytest.approx(-0.01)
        else:
            with pytest.raises(BagError, match="outer_insertion") as err:
                read_bag(path)
            assert "limits1.bag" in str(err.value)


def test_the_topic_maps_robot_key(tmp_path):
    path = tmp_path / "run.bag"
    write_dvrk_bag(path, "ros1", duration=0.1)
    body = (
        '[[source]]\nstream = "psm_joints"\narm = "psm2"\ntopic = "/PSM2/measured_js"\n'
        'type = "sensor_msgs/msg/JointState"\nfield = "position"\n'
    )
    for head, robot in (
        ("", "simulator"),
        ('robot = "dvrk"\n', "dvrk"),
        ('robot = "auto"\n', "dvrk"),
    ):
        tmap = tmp_path / f"map_{robot}_{len(head)}.toml"
        tmap.write_text(head + body, encoding="utf-8")
        assert read_bag(path, topic_map=tmap).robot == robot
    tmap.write_text('robot = "ambf"\n' + body, encoding="utf-8")
    with pytest.raises(BagError, match="robot"):
        read_bag(path, topic_map=tmap)
