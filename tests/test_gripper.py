"""The parallel gripper: a friction-only grasp holds a known weight, and the forces read back
are the physical ones."""

import mujoco
import numpy as np
import pytest

from liuxing_envs.sim.arm import Arm
from liuxing_envs.sim.gripper import TCP_SITE, Gripper, attach_gripper
from liuxing_envs.sim.scene import ARM_ACTUATOR_NAMES, load_scene_spec, reset_to_home

WEIGHT_MASS = 0.1  # kg
WEIGHT_WIDTH = 0.02  # m across the jaws
GRAVITY = 9.81
SERVO_STIFFNESS = 5000.0  # N/m, the finger servos' kp (assets/parallel_gripper.xml)
TOOL_DOWN = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])


def grasp_and_lift(grip_force: float, lift: float = 0.1):
    """Pinch a 100 g block with ``grip_force`` per pad, raise the arm by ``lift`` under
    physics, hold 2 s. Returns the block's rise, its slip relative to the tool, and the
    gripper and model for inspection."""
    spec = load_scene_spec()
    attach_gripper(spec)
    block = spec.worldbody.add_body(name="weight", pos=[0.5, 0.0, 0.02])
    block.add_freejoint()
    block.add_geom(
        type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.015, WEIGHT_WIDTH / 2, 0.02], mass=WEIGHT_MASS
    )
    model = spec.compile()
    data = mujoco.MjData(model)
    reset_to_home(model, data)
    arm, gripper = Arm(model, data), Gripper(model, data)
    grasp = arm.solve_ik([0.5, 0.0, 0.02], TOOL_DOWN, site=TCP_SITE, check_collisions=False)
    above = arm.solve_ik(
        [0.5, 0.0, 0.02 + lift],
        TOOL_DOWN,
        site=TCP_SITE,
        seed_qpos=grasp.qpos,
        check_collisions=False,
    )
    assert grasp.success and above.success
    gripper.set_opening(0.06)  # start open around the block
    arm.set_qpos(grasp.qpos)
    mujoco.mj_step(model, data, nstep=100)
    # Position servos: pressing with F needs a target F / kp inside the surface, per finger.
    gripper.command(WEIGHT_WIDTH - 2 * grip_force / SERVO_STIFFNESS)
    mujoco.mj_step(model, data, nstep=250)
    start_height = data.body("weight").xpos[2]
    arm_actuators = [model.actuator(name).id for name in ARM_ACTUATOR_NAMES]
    for k in range(1, 501):  # 1 s: smooth set-point ramp up, then settle
        s = min(1.0, k / 400)
        data.ctrl[arm_actuators] = grasp.qpos + (above.qpos - grasp.qpos) * (3 * s * s - 2 * s**3)
        mujoco.mj_step(model, data)
    offset_before = data.body("weight").xpos - data.site(TCP_SITE).xpos
    mujoco.mj_step(model, data, nstep=1000)  # hold for 2 s
    offset_after = data.body("weight").xpos - data.site(TCP_SITE).xpos
    rise = data.body("weight").xpos[2] - start_height
    slip = np.linalg.norm(offset_after - offset_before)
    assert np.sum(data.warning.number) == 0
    return rise, slip, gripper, model


def test_a_firm_friction_grasp_holds_the_weight_and_reads_the_right_forces():
    grip = 8.0  # N per pad: 2 * mu * N = 16 N of friction against 0.98 N of weight
    rise, slip, gripper, model = grasp_and_lift(grip)
    assert rise == pytest.approx(0.1, abs=2e-3)
    assert slip < 1e-4  # less than 0.1 mm of creep over a 2 s hold (noslip iterations)
    touch = gripper.fingertip_forces()
    np.testing.assert_allclose(touch, grip, rtol=0.1)
    np.testing.assert_allclose(-gripper.actuator_forces(), touch, rtol=0.02)
    # Everything the block touches (only the pads now) carries exactly its weight.
    net = gripper.contact_force_on(model.body("weight").id)
    np.testing.assert_allclose(net, [0.0, 0.0, WEIGHT_MASS * GRAVITY], atol=1e-3)


def test_a_grip_too_weak_for_friction_leaves_the_weight_behind():
    # 2 * mu * N = 0.4 N < m g = 0.98 N: friction cannot carry it, nothing else holds it.
    rise, _, gripper, _ = grasp_and_lift(0.2)
    assert rise < 1e-3
    np.testing.assert_allclose(gripper.fingertip_forces(), 0.0, atol=1e-9)


def test_squeezing_is_possible_and_limited_by_the_servo_force():
    rise, _, gripper, _ = grasp_and_lift(grip_force=200.0)  # asks for far more than 40 N
    assert rise == pytest.approx(0.1, abs=2e-3)
    np.testing.assert_allclose(gripper.fingertip_forces(), gripper.max_force, rtol=0.05)
    assert gripper.max_force == 40.0
