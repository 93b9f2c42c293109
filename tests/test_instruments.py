"""Surgical instruments and the tray: geometry, masses, resting, grasping and colour, simulated
and rendered with real MuJoCo."""

import cv2
import mujoco
import numpy as np
import pytest

from liuxing_envs.sim.instruments import (
    DEFAULT_FRICTION,
    DEFAULT_INSTRUMENT_PRIORITY,
    DEFAULT_SOLIMP,
    DEFAULT_SOLREF,
    DEFAULT_TRAY_PRIORITY,
    INSTRUMENT_NAMES,
    INSTRUMENT_SETS,
    Instrument,
    InstrumentPart,
    add_instrument,
    add_tray,
    get_instrument,
    instrument_names,
)
from liuxing_envs.sim.scene import load_scene_spec, reset_to_home

PREFIX = "ins_"
DROP_HEIGHT = 0.02  # m, lowest point above the tray floor
SETTLE_TIME = 1.0  # s
MAX_PENETRATION = 0.001  # m
#: Noslip iterations the grasp environment runs with, and the scene's default (none).
NOSLIP = (0, 10)


def _scene(instrument, *, pos=None, quat=(1.0, 0.0, 0.0, 0.0), noslip=0, **kwargs):
    """Tabletop scene + tray + one instrument (at rest on the tray's centre by default)."""
    spec = load_scene_spec()
    spec.option.noslip_iterations = noslip
    tray = add_tray(spec)
    if pos is None:
        pos = (*tray.center, tray.floor_z)
    add_instrument(spec, instrument, PREFIX, pos=pos, quat=quat, **kwargs)
    return spec, tray


def _compile(spec):
    model = spec.compile()
    data = mujoco.MjData(model)
    reset_to_home(model, data)
    return model, data


def _yaw_quat(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def _penetration(model, data, body_a: int, body_b: int) -> float:
    """Deepest overlap (m) among contacts between two bodies, 0 if none."""
    contacts = data.contact
    bodies = np.sort(model.geom_bodyid[contacts.geom[: data.ncon]], axis=1)
    pair = np.all(bodies == sorted((body_a, body_b)), axis=1)
    return float(max(0.0, -contacts.dist[: data.ncon][pair].min(initial=np.inf)))


def _inside_geom(model, data, geom: int, point: np.ndarray, tol: float = 1e-6) -> bool:
    """Whether ``point`` (world) lies on or inside primitive geom ``geom``."""
    local = data.geom_xmat[geom].reshape(3, 3).T @ (point - data.geom_xpos[geom])
    size = model.geom_size[geom]
    kind = model.geom_type[geom]
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        return bool(np.all(np.abs(local) <= size + tol))
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
        nearest = np.array([0.0, 0.0, np.clip(local[2], -size[1], size[1])])
        return bool(np.linalg.norm(local - nearest) <= size[0] + tol)
    if kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return bool(abs(local[2]) <= size[1] + tol and np.hypot(*local[:2]) <= size[0] + tol)
    if kind == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        return bool(np.sum((local / size) ** 2) <= 1.0 + tol)
    raise AssertionError(f"unexpected geom type {kind}")


# --- the library -----------------------------------------------------------------------------


def test_library_covers_the_required_instruments():
    required = {"scalpel", "tissue_forceps", "scissors", "needle_holder", "hemostat"}
    assert required <= set(INSTRUMENT_NAMES)
    assert {"probe", "retractor"} & set(INSTRUMENT_NAMES)
    assert len(INSTRUMENT_NAMES) >= 6 and len(set(INSTRUMENT_NAMES)) == len(INSTRUMENT_NAMES)


def test_split_is_disjoint_and_covers_all():
    train, held_out = set(INSTRUMENT_SETS["train"]), set(INSTRUMENT_SETS["held_out"])
    assert train and held_out and not train & held_out
    assert train | held_out == set(INSTRUMENT_SETS["all"]) == set(INSTRUMENT_NAMES)
    assert instrument_names("held_out") == INSTRUMENT_SETS["held_out"]
    assert instrument_names() == INSTRUMENT_NAMES
    with pytest.raises(ValueError, match="train, held_out, all"):
        instrument_names("test")


def test_unknown_instrument_names_the_valid_ones():
    with pytest.raises(ValueError, match="valid instruments: scalpel, tissue_forceps"):
        get_instrument("trocar")


@pytest.mark.parametrize("name", INSTRUMENT_NAMES)
def test_instrument_is_sized_coloured_and_grounded(name):
    instrument = get_instrument(name)
    assert instrument.name == name and get_instrument(name) is instrument
    low, high = instrument.bounding_box
    assert 0.12 <= instrument.length <= 0.20
    assert 0.010 <= instrument.mass <= 0.150
    assert 0.005 <= instrument.grasp_width <= 0.025
    assert len(instrument.parts) <= 12
    assert {part.role for part in instrument.parts} == {"handle", "steel"}
    assert low[2] == pytest.approx(0.0, abs=1e-9)  # lying on z = 0
    assert low[:2] == pytest.approx(-high[:2], abs=1e-9)  # centred in x and y
    assert instrument.part_masses().sum() == pytest.approx(instrument.mass, rel=1e-12)
    for part in instrument.parts:
        radius_like = part.size[0] if part.type in ("capsule", "cylinder") else min(part.size)
        assert radius_like >= (0.0015 if part.type in ("capsule", "cylinder") else 0.001) - 1e-12


def test_descriptions_reject_unphysical_instruments():
    handle = InstrumentPart("handle", "box", (0.07, 0.005, 0.002), (0, 0, 0.002), role="handle")
    good = dict(
        name="x", parts=(handle,), mass=0.02, grasp_point=(0, 0, 0.002), grasp_axis=(1, 0, 0)
    )
    assert Instrument(**good, grasp_width=0.01).length == pytest.approx(0.14)
    with pytest.raises(ValueError, match="too thin"):
        InstrumentPart("foil", "box", (0.05, 0.01, 0.0005), (0, 0, 0.0005))
    with pytest.raises(ValueError, match="too thin"):
        InstrumentPart("wire", "capsule", (0.001, 0.05), (0, 0, 0.001))
    with pytest.raises(ValueError, match="graspable"):
        Instrument(**good, grasp_width=0.03)
    with pytest.raises(ValueError, match="z = 0"):
        raised = InstrumentPart("handle", "box", (0.07, 0.005, 0.002), (0, 0, 0.01), role="handle")
        Instrument(**{**good, "parts": (raised,)}, grasp_width=0.01)
    with pytest.raises(ValueError, match="mass"):
        Instrument(**{**good, "mass": 0.5}, grasp_width=0.01)
    with pytest.raises(ValueError, match="inside a handle"):
        Instrument(**{**good, "grasp_point": (0.09, 0, 0.002)}, grasp_width=0.01)


# --- in the compiled scene -------------------------------------------------------------------


@pytest.mark.parametrize("name", INSTRUMENT_NAMES)
def test_compiled_mass_and_contact_parameters(name):
    instrument = get_instrument(name)
    model, _ = _compile(_scene(name)[0])
    body = model.body(f"{PREFIX}body")
    mass = float(model.body_subtreemass[body.id])
    assert 0.010 <= mass <= 0.150
    assert mass == pytest.approx(instrument.mass, rel=0.01)
    assert model.jnt_type[body.jntadr[0]] == mujoco.mjtJoint.mjJNT_FREE
    geoms = [model.geom(geom_name) for geom_name in instrument.geom_names(PREFIX)]
    assert all(geom.bodyid[0] == body.id for geom in geoms)
    assert all(geom.condim[0] == 4 for geom in geoms)  # torsional friction for a pinch grasp
    assert all(geom.friction == pytest.approx(DEFAULT_FRICTION) for geom in geoms)
    assert all(geom.solref == pytest.approx(DEFAULT_SOLREF) for geom in geoms)
    assert all(geom.solimp == pytest.approx(DEFAULT_SOLIMP) for geom in geoms)
    floor = model.geom("tray_floor")
    assert floor.priority[0] == DEFAULT_TRAY_PRIORITY > DEFAULT_INSTRUMENT_PRIORITY
    assert model.site(f"{PREFIX}grasp").bodyid[0] == body.id

    heavier, _ = _compile(_scene(name, mass_scale=1.5)[0])
    heavier_mass = heavier.body_subtreemass[heavier.body(f"{PREFIX}body").id]
    assert heavier_mass == pytest.approx(1.5 * instrument.mass, rel=1e-6)


@pytest.mark.parametrize("name", INSTRUMENT_NAMES)
def test_length_measured_by_rays_matches_the_description(name):
    """Rays along x over the instrument's cross-section find its ends where the bounding box
    says, so the 12-20 cm lengths hold for the compiled geoms, not only for the description."""
    instrument = get_instrument(name)
    spec, tray = _scene(name)
    model, data = _compile(spec)
    mujoco.mj_forward(model, data)
    low, high = instrument.bounding_box
    origin = np.array([*tray.center, tray.floor_z])
    step = 0.00025
    ys, zs = (np.arange(low[i] + step / 2, high[i], step) for i in (1, 2))
    ends = []
    for sign in (1.0, -1.0):
        start_x, direction = sign * 0.2, np.array([-sign, 0.0, 0.0])
        nearest = np.inf
        for y in ys:
            for z in zs:
                start = origin + (start_x, y, z)
                dist = mujoco.mj_ray(model, data, start, direction, None, 0, -1, None)
                if dist >= 0:
                    nearest = min(nearest, dist)
        ends.append(sign * (0.2 - nearest))
    measured = ends[0] - ends[1]
    assert ends == pytest.approx([high[0], low[0]], abs=1e-4)
    assert 0.12 <= measured <= 0.20


@pytest.mark.parametrize("name", INSTRUMENT_NAMES)
def test_grasp_site_lies_in_the_handle_at_the_declared_width(name):
    instrument = get_instrument(name)
    yaw = np.random.default_rng(1).uniform(-np.pi, np.pi)
    model, data = _compile(_scene(name, quat=_yaw_quat(yaw))[0])
    mujoco.mj_forward(model, data)
    site = model.site(f"{PREFIX}grasp").id
    centre = data.site_xpos[site].copy()
    axis, jaw, up = data.site_xmat[site].reshape(3, 3).T
    assert up == pytest.approx([0, 0, 1], abs=1e-9)
    handle = {model.geom(g).id for g in instrument.geom_names(PREFIX, "handle")}
    assert any(_inside_geom(model, data, g, centre) for g in handle)

    # Close "jaws" along the site's y axis at the pad's centre and both ends (pads ~2 cm long):
    # rays from 4 cm out (half the 8 cm opening) meet only handle geoms, at the declared width.
    reach = 0.04
    for offset in (-0.008, 0.0, 0.008):
        point = centre + offset * axis
        width = 2 * reach
        for direction in (jaw, -jaw):
            geom = np.array([-1], dtype=np.int32)
            dist = mujoco.mj_ray(
                model, data, point - reach * direction, direction, None, 0, -1, geom
            )
            assert dist >= 0 and geom[0] in handle, f"{name}: jaw at {offset} m meets {geom[0]}"
            width -= dist
        assert width == pytest.approx(instrument.grasp_width, abs=5e-4)


@pytest.mark.parametrize("noslip", NOSLIP)
@pytest.mark.parametrize("name", INSTRUMENT_NAMES)
def test_dropped_instrument_comes_to_rest_flat_on_the_tray(name, noslip):
    """Released level 2 cm above the tray (as an environment places one, at a random position
    and yaw), it settles flat within 1 s without sinking more than 1 mm into the tray. Landings
    on one end sink deeper at the 2 ms timestep; see the module docstring."""
    rng = np.random.default_rng([INSTRUMENT_NAMES.index(name), noslip])
    spec = load_scene_spec()
    spec.option.noslip_iterations = noslip
    tray = add_tray(spec)
    xy = np.asarray(tray.center) + rng.uniform(-0.05, 0.05, size=2)
    quat = _yaw_quat(rng.uniform(-np.pi, np.pi))
    add_instrument(spec, name, PREFIX, pos=(*xy, tray.floor_z + DROP_HEIGHT), quat=quat)
    model, data = _compile(spec)
    body, tray_body = model.body(f"{PREFIX}body").id, model.body(tray.body_name).id

    steps = round(SETTLE_TIME / model.opt.timestep)
    deepest, speeds, positions = 0.0, [], []
    for _ in range(steps):
        mujoco.mj_step(model, data)
        deepest = max(deepest, _penetration(model, data, body, tray_body))
        speeds.append(np.abs(data.cvel[body]))  # (angular, linear)
        positions.append(data.xpos[body].copy())

    assert not any(warning.number for warning in data.warning), "MuJoCo warned"
    assert deepest <= MAX_PENETRATION, f"penetrated the tray by {deepest * 1e3:.2f} mm"
    last = slice(-round(0.1 / model.opt.timestep), None)  # the last 0.1 s
    speeds = np.array(speeds)
    assert speeds[last, 3:].max() < 1e-3  # m/s
    assert speeds[last, :3].max() < 1e-2  # rad/s
    assert np.ptp(np.array(positions)[last], axis=0).max() < 1e-4
    up = data.xmat[body].reshape(3, 3)[:, 2]
    assert np.degrees(np.arccos(min(1.0, up[2]))) < 0.5  # lying flat
    # The frame's origin is the lowest point: it rests on the floor, not in or above it.
    assert data.xpos[body][2] == pytest.approx(tray.floor_z, abs=2e-4)


@pytest.mark.parametrize("name", INSTRUMENT_NAMES)
def test_gentle_pinch_lifts_the_instrument_by_friction(name):
    """Two pads pressed onto the handle with 5 N each lift the instrument 5 cm by friction."""
    force, lift, noslip = 5.0, 0.05, 10
    instrument = get_instrument(name)
    spec, tray = _scene(name, noslip=noslip)
    grasp = np.asarray(instrument.grasp_point) + (*tray.center, tray.floor_z)
    hand = spec.worldbody.add_body(name="hand", pos=grasp.tolist(), gravcomp=1)
    hand.add_joint(name="lift", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, 0, 1])
    hand.add_geom(size=[0.01, 0, 0], mass=0.2, contype=0, conaffinity=0, pos=[0, 0, 0.05])
    lifter = spec.add_actuator(name="lift", target="lift", trntype=mujoco.mjtTrn.mjTRN_JOINT)
    lifter.set_to_position(kp=2000, kv=100)
    pad_half = (0.01, 0.004, 0.01)  # 2 cm long, 2 cm tall, hovering 0.5 mm over the floor
    pad_z = pad_half[2] + 0.0005 - instrument.grasp_point[2]
    for side, sign in (("left", 1), ("right", -1)):
        pad_y = sign * (instrument.grasp_width / 2 + pad_half[1] + 0.001)
        pad = hand.add_body(name=f"pad_{side}", pos=[0, pad_y, pad_z], gravcomp=1)
        pad.add_joint(name=side, type=mujoco.mjtJoint.mjJNT_SLIDE, axis=[0, -sign, 0], damping=2.0)
        pad.add_geom(
            name=f"pad_{side}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=list(pad_half),
            mass=0.05,
            friction=list(DEFAULT_FRICTION),
            condim=4,
            solref=list(DEFAULT_SOLREF),
            solimp=list(DEFAULT_SOLIMP),
        )
        spec.add_actuator(name=side, target=side, trntype=mujoco.mjtTrn.mjTRN_JOINT)
    model, data = _compile(spec)
    body, hand_id = model.body(f"{PREFIX}body").id, model.body("hand").id
    pads = [model.body(f"pad_{side}").id for side in ("left", "right")]
    data.ctrl[[model.actuator("left").id, model.actuator("right").id]] = force

    squeeze_time, lift_speed = 0.3, 0.05  # s, m/s
    offsets, deepest = [], 0.0
    for _ in range(round((squeeze_time + lift / lift_speed + 0.2) / model.opt.timestep)):
        data.ctrl[model.actuator("lift").id] = np.clip(
            lift_speed * (data.time - squeeze_time), 0.0, lift
        )
        mujoco.mj_step(model, data)
        deepest = max(deepest, *(_penetration(model, data, body, pad) for pad in pads))
        if data.time > squeeze_time:
            offsets.append(data.xpos[hand_id][2] - data.xpos[body][2])

    assert not any(warning.number for warning in data.warning), "MuJoCo warned"
    assert data.xpos[body][2] - tray.floor_z == pytest.approx(lift, abs=0.003)
    assert np.ptp(offsets) < 5e-4, f"slipped {np.ptp(offsets) * 1e3:.2f} mm"
    assert deepest < MAX_PENETRATION, f"pads sank {deepest * 1e3:.2f} mm"
    up = data.xmat[body].reshape(3, 3)[:, 2]
    assert np.degrees(np.arccos(min(1.0, up[2]))) < 2.0  # held level, not swinging


def test_tray_is_static_and_optionally_flat():
    spec = load_scene_spec()
    tray = add_tray(spec, center=(0.45, 0.05))
    flat = add_tray(spec, center=(0.45, 0.5), rim_height=0.0, name_prefix="plate_")
    model = spec.compile()
    assert len(tray.geom_names) == 5 and flat.geom_names == ("plate_floor",)
    for name in tray.geom_names + flat.geom_names:
        assert model.body_weldid[model.geom(name).bodyid[0]] == 0  # welded to the world
    assert tray.center == (0.45, 0.05) and tray.floor_z == pytest.approx(0.004)
    assert tray.inner_half_size == pytest.approx((0.145, 0.195))
    assert flat.inner_half_size == pytest.approx((0.15, 0.2))


# --- colour ----------------------------------------------------------------------------------


def _red_mask(rgb: np.ndarray) -> np.ndarray:
    """The seed pipeline's HSV threshold for a red handle (OpenCV hue 0-180 wraps at red)."""
    hsv = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)
    hue, saturation, value = hsv[..., 0], hsv[..., 1], hsv[..., 2]
    return ((hue <= 10) | (hue >= 170)) & (saturation >= 100) & (value >= 60)


def test_handles_render_red_and_steel_does_not():
    spec = load_scene_spec()
    tray = add_tray(spec, size=(0.40, 0.52))
    # Two columns of instruments, each lying along x, in a fixed seeded layout.
    rng = np.random.default_rng(7)
    for i, name in enumerate(INSTRUMENT_NAMES):
        column, row = divmod(i, 4)
        x = tray.center[0] + (-0.09 if column == 0 else 0.09)
        y = -0.18 + 0.12 * row
        add_instrument(
            spec,
            name,
            f"{name}_",
            pos=(x, y, tray.floor_z),
            quat=_yaw_quat(rng.uniform(-0.2, 0.2)),
        )
    spec.worldbody.add_camera(name="above", pos=[tray.center[0], 0.0, 0.6], fovy=50)
    model, data = _compile(spec)
    mujoco.mj_forward(model, data)
    with mujoco.Renderer(model, 480, 480) as renderer:
        renderer.update_scene(data, "above")
        red = _red_mask(renderer.render())
        renderer.enable_segmentation_rendering()
        segmentation = renderer.render()
    geom_ids = np.where(segmentation[..., 1] == mujoco.mjtObj.mjOBJ_GEOM, segmentation[..., 0], -1)

    def interior(geom_names) -> np.ndarray:
        """Pixels of these geoms away from their outline (edges blend with the neighbours)."""
        mask = np.isin(geom_ids, [model.geom(g).id for g in geom_names]).astype(np.uint8)
        return cv2.erode(mask, np.ones((3, 3), np.uint8)).astype(bool)

    for name in INSTRUMENT_NAMES:
        instrument = get_instrument(name)
        handle = interior(instrument.geom_names(f"{name}_", "handle"))
        steel = interior(instrument.geom_names(f"{name}_", "steel"))
        assert handle.sum() >= 100 and steel.sum() >= 20, f"{name} barely visible"
        assert red[handle].mean() >= 0.98, f"{name}: handle only {red[handle].mean():.0%} red"
        assert not red[steel].any(), f"{name}: {red[steel].sum()} steel pixels look red"
    tray_pixels = interior(tray.geom_names)
    assert tray_pixels.sum() > 0.3 * red.size and not red[tray_pixels].any()
