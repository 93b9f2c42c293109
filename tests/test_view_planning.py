"""ViewPlanning-v1 (and the deprecated v0): API, reward bookkeeping, coverage, bad input."""

import gc
import pickle
import warnings
import weakref

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from stable_baselines3.common.env_checker import check_env as sb3_check_env

import liuxing_envs  # noqa: F401  (registers the ids)
from agents.view_baselines import FourViewpointBaseline, GreedyOracle, RandomViews, UniformViews
from liuxing_envs import forking
from liuxing_envs.envs.view_planning import ViewPlanningEnv, ViewPlanningV0Env
from liuxing_envs.envs.view_planning_settings import V0, V1
from liuxing_envs.perception.pointcloud import camera_rays
from liuxing_envs.sim.viewpoints import look_at
from tests.scripts import outcomes_without_opengl

ENV_ID = "ViewPlanning-v1"
#: Small and fast settings shared by most tests (3 objects, one scale).
FAST = {"objects": ["box", "mug", "cylinder"], "scales": (1.0,), "coverage_samples": 2048}


@pytest.fixture(scope="module")
def env():
    env = gym.make(ENV_ID, **FAST)
    yield env
    env.close()


def run_episode(env, policy, seed):
    obs, info = env.reset(seed=seed)
    infos, rewards = [info], []
    done = False
    while not done:
        action, _ = policy.predict(obs, deterministic=True)
        obs, reward, terminated, truncated, info = env.step(action)
        infos.append(info)
        rewards.append(reward)
        done = terminated or truncated
    return obs, rewards, infos


def test_v1_is_registered_without_a_time_limit_and_v0_with_its_budget_of_4():
    assert gym.spec(ENV_ID).max_episode_steps is None
    assert gym.spec("ViewPlanning-v0").max_episode_steps == V0.task.view_budget == 4
    env = gym.make("liuxing_envs:ViewPlanning-v1", **FAST)
    assert isinstance(env.unwrapped, ViewPlanningEnv)
    assert env.unwrapped.settings.differences(V1) == {
        name: (value, V1.flat()[name]) for name, value in env.unwrapped.settings.flat().items()
        if name in FAST
    }  # fmt: skip
    env.close()


@pytest.mark.parametrize("budget", [1, 8])
def test_v1_runs_any_view_budget_to_its_end(budget):
    """ViewPlanning-v0's registered time limit cut view_budget=8 short after 4 views."""
    env = gym.make(ENV_ID, view_budget=budget, **FAST)
    env.reset(seed=0)
    flags = []
    for _ in range(budget):
        _, _, terminated, truncated, info = env.step(env.action_space.sample())
        flags.append((terminated, truncated))
    assert flags == [(False, False)] * (budget - 1) + [(True, False)]
    assert info["views_used"] == budget
    env.close()


def test_v0_warns_naming_v1_and_keeps_its_depth_backend():
    with pytest.warns(DeprecationWarning, match=r"ViewPlanning-v0 is deprecated.*ViewPlanning-v1"):
        env = gym.make("ViewPlanning-v0", **FAST)
    assert isinstance(env.unwrapped, ViewPlanningV0Env)
    assert env.unwrapped.settings.sensor.depth_backend == "auto" == V0.sensor.depth_backend
    assert V1.differences(V0) == {"depth_backend": ("raycast", "auto")}
    env.close()


def test_spending_the_budget_is_a_terminal_state_learners_do_not_bootstrap_from():
    # It was a truncation: SB3 then added the critic's guess of a state with no views left
    # (about 0.5, against 0.08 for a last view's reward) to every episode's last reward.
    from stable_baselines3.common.vec_env import DummyVecEnv

    env = DummyVecEnv([lambda: gym.make(ENV_ID, view_budget=3, max_episode_steps=5, **FAST)])
    env.seed(0)
    env.reset()
    for step in range(3):
        _, _, dones, infos = env.step(np.zeros((1, 3), dtype=np.float32))
        assert dones[0] == (step == 2)
    assert not infos[0]["TimeLimit.truncated"]
    # The registered TimeLimit at the budget flags truncated too, still not as a timeout.
    plain = gym.make(ENV_ID, view_budget=2, max_episode_steps=2, **FAST)
    plain.reset(seed=0)
    plain.step(np.zeros(3, dtype=np.float32))
    _, _, terminated, truncated, _ = plain.step(np.zeros(3, dtype=np.float32))
    assert terminated and truncated
    # A TimeLimit shorter than the budget cuts the episode: a truncation, views left.
    short = DummyVecEnv([lambda: gym.make(ENV_ID, view_budget=4, max_episode_steps=2, **FAST)])
    short.seed(0)
    short.reset()
    short.step(np.zeros((1, 3), dtype=np.float32))
    _, _, dones, infos = short.step(np.zeros((1, 3), dtype=np.float32))
    assert dones[0] and infos[0]["TimeLimit.truncated"]


def test_the_arm_in_view_is_filtered_out_of_the_map_not_out_of_the_image():
    # Seed 0's view 3 (azimuth -45 deg, elevation 25 deg) shows the upper arm: it was fused
    # as object, into the map, the coverage and the reconstruction.
    import mujoco

    filtered = ViewPlanningEnv(action_mode="discrete", depth_backend="raycast", **FAST)
    raw = ViewPlanningEnv(
        action_mode="discrete", depth_backend="raycast", filter_arm_points=False, **FAST
    )
    observations = []
    for env in (filtered, raw):
        env.reset(seed=0)
        observations.append(env.step(3)[0])
    np.testing.assert_array_equal(observations[0]["depth"], observations[1]["depth"])
    on_arm = filtered.camera.pixels_on_geoms(
        filtered.depth, filtered.data, filtered.arm.geom_ids, 0.003
    )
    assert on_arm.sum() > 300
    # Which geom each pixel's ray meets first, by MuJoCo's own ray caster.
    position, rotation = filtered.camera.pose(filtered.data)
    rays = camera_rays(filtered.camera.intrinsics, "unit") @ rotation.T
    first_hit = np.zeros(1, dtype=np.int32)
    arm = set(filtered.arm.geom_ids.tolist())
    hits_arm = np.zeros_like(on_arm)
    for row, col in zip(*np.nonzero(filtered.depth > 0), strict=True):
        groups = np.array([1, 1, 1, 0, 0, 0], dtype=np.uint8)
        mujoco.mj_ray(
            filtered.model, filtered.data, position, rays[row, col], groups, 1, -1, first_hit
        )
        hits_arm[row, col] = int(first_hit[0]) in arm
    assert (hits_arm <= on_arm).all()  # every return on the arm is found
    assert (on_arm & ~hits_arm).sum() <= 0.05 * on_arm.sum()  # and little else, at its rim
    assert len(raw.map.points()) - len(filtered.map.points()) >= 10  # cells of arm only


def test_passes_gymnasium_env_checker():
    env = ViewPlanningEnv(**FAST)
    check_env(env, skip_render_check=True)
    env.close()


def test_passes_sb3_env_checker():
    for action_mode in ("continuous", "discrete"):
        env = ViewPlanningEnv(action_mode=action_mode, **FAST)
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # SB3's advice on spaces counts as a failure here
            sb3_check_env(env, warn=True)
        env.close()


def test_reward_terms_sum_to_the_reward_and_coverage_is_monotone(env):
    _, rewards, infos = run_episode(env, RandomViews(env, seed=3), seed=11)
    assert len(rewards) == 4
    coverages = [info["coverage"] for info in infos]
    assert all(0.0 <= c <= 1.0 for c in coverages)
    assert np.all(np.diff(coverages) >= 0)
    assert coverages[0] > 0  # the start view sees the object
    for reward, info in zip(rewards, infos[1:], strict=True):
        terms = info["reward_coverage"] + info["reward_motion"] + info["reward_refusal"]
        assert reward == pytest.approx(terms)
        assert info["reward_coverage"] == pytest.approx(10.0 * info["coverage_gain"])
        assert info["reward_motion"] == pytest.approx(-0.01 * info["path_length"])
        assert info["reward_refusal"] == (-0.1 if info["refused"] else 0.0)
    assert infos[-1]["coverage"] == pytest.approx(
        infos[0]["coverage"] + sum(i["coverage_gain"] for i in infos[1:])
    )


def test_same_seed_same_episode_and_different_seeds_differ(env):
    first = run_episode(env, FourViewpointBaseline(env), seed=5)
    second = run_episode(env, FourViewpointBaseline(env), seed=5)
    np.testing.assert_array_equal(first[0]["depth"], second[0]["depth"])
    assert first[1] == second[1]
    placements = set()
    for seed in range(6):
        env.reset(seed=seed)
        placed = env.unwrapped.placed
        placements.add((placed.name, round(float(placed.position[0]), 6), round(placed.yaw, 6)))
    assert len(placements) == 6
    assert len({p[0] for p in placements}) > 1


def test_a_view_of_nothing_earns_no_coverage():
    env = ViewPlanningEnv(**FAST)
    env.reset(seed=0)
    # Look away from the object: straight down at the table far off to the side.
    env.unwrapped.center = np.array([0.45, 0.35, 0.0])
    _, reward, _, _, info = env.step(env.view_to_action(0.0, np.pi / 2, 0.35))
    assert info["reachable"] and info["coverage_gain"] == 0.0
    assert reward == pytest.approx(info["reward_motion"])
    env.close()


def test_four_view_coverage_is_high_but_the_oracle_does_better():
    env = ViewPlanningEnv(action_mode="discrete", **FAST)
    four, oracle = FourViewpointBaseline(env), GreedyOracle(env)
    four_final = [run_episode(env, four, seed)[2][-1]["coverage"] for seed in range(3)]
    oracle_final = [run_episode(env, oracle, seed)[2][-1]["coverage"] for seed in range(3)]
    assert np.mean(four_final) > 0.5
    assert np.mean(oracle_final) > np.mean(four_final) + 0.03
    env.close()


def test_uniform_views_spread_around_the_object(env):
    _, _, infos = run_episode(env, UniformViews(env), seed=2)
    azimuths = sorted(round(info["viewpoint"][0]) for info in infos[1:])
    assert azimuths == [-135, -45, 45, 135]


def test_unreachable_view_is_refused_and_penalised():
    env = ViewPlanningEnv(**FAST)
    env.reset(seed=1)
    before = env.unwrapped.arm.qpos
    # Far side, grazing elevation, largest radius: beyond the arm's reach.
    _, reward, _, _, info = env.step(env.view_to_action(0.0, np.deg2rad(20), 0.45))
    assert info["refused"] and not info["reachable"]
    assert reward == pytest.approx(-0.1)
    np.testing.assert_array_equal(env.unwrapped.arm.qpos, before)
    env.close()


#: Seed 1 (the mug) reaches the first view and refuses the second (beyond the arm's reach).
REACHED_VIEW = (np.deg2rad(60.0), np.deg2rad(50.0), 0.36)
REFUSED_VIEW = (np.deg2rad(-30.0), np.deg2rad(20.0), 0.45)
#: The keys the docstring lists for reset()'s info; a step's info adds the other four.
RESET_INFO_KEYS = {
    "coverage",
    "coverage_gain",
    "views_used",
    "reachable",
    "refused",
    "path_length",
    "is_success",
    "object",
    "scale",
    "sim_unstable",
}
STEP_ONLY_INFO_KEYS = {"reward_coverage", "reward_motion", "reward_refusal", "viewpoint"}


def test_reaching_success_coverage_ends_the_episode_only_when_asked():
    """is_success is coverage >= success_coverage, at the threshold too, and the episode
    ends there only with terminate_on_success. Catches a success clause dropped from
    ``terminated``, an is_success stuck at False or True, and ``>`` for ``>=``."""
    side = (np.pi / 2, np.pi / 4, 0.38)
    plain = ViewPlanningEnv(**FAST)
    start = plain.reset(seed=0)[1]["coverage"]
    reached = plain.step(plain.view_to_action(*side))[-1]["coverage"]
    assert 0.0 < start < reached < 1.0
    plain.close()
    for threshold in (reached, np.nextafter(reached, 1.0)):
        for stop in (True, False):
            env = ViewPlanningEnv(success_coverage=threshold, terminate_on_success=stop, **FAST)
            _, info = env.reset(seed=0)
            assert not info["is_success"]
            _, _, terminated, truncated, info = env.step(env.view_to_action(*side))
            assert info["coverage"] == reached and info["views_used"] == 1  # 3 views left
            assert info["is_success"] == (threshold == reached)
            assert terminated == (stop and threshold == reached) and not truncated
            env.close()
    # The start view's coverage already at the threshold: reset() reports the success.
    env = ViewPlanningEnv(success_coverage=start, terminate_on_success=True, **FAST)
    assert env.reset(seed=0)[1]["is_success"]
    env.close()


def test_budget_camera_pose_and_view_history_observations_follow_the_docstring():
    """The vector observations, against values computed from the views requested: catches
    a budget share that does not count down (or counts against the default budget), a
    camera pose not relative to the centre or with a flipped axis, and a view-history entry
    with its features swapped, unnormalised or its reached/refused flag wrong."""
    budget = 5  # not the default 4, so a share of the default budget shows
    env = ViewPlanningEnv(view_budget=budget, **FAST)
    low, high = env.radius_range

    def pose_of_camera():
        position, rotation = env.camera.pose(env.data)
        return np.concatenate([position - env.center, -rotation[:, 2], rotation[:, 1]])

    obs, _ = env.reset(seed=1)
    assert obs["budget"].tolist() == [1.0]
    assert obs["view_history"].shape == (budget * 5,) and not obs["view_history"].any()
    np.testing.assert_allclose(obs["camera_pose"], pose_of_camera(), atol=1e-6)
    np.testing.assert_allclose(obs["camera_pose"][3:6], [0, 0, -1], atol=1e-5)  # looks down
    history = np.zeros((budget, 5))
    for used, (view, reached) in enumerate(((REACHED_VIEW, True), (REFUSED_VIEW, False)), 1):
        before = obs["camera_pose"]
        obs, *_, info = env.step(env.view_to_action(*view))
        assert info["refused"] != reached
        azimuth, elevation, radius = view
        history[used - 1] = [
            np.cos(azimuth),
            np.sin(azimuth),
            np.rad2deg(elevation) / 90.0,
            (radius - low) / (high - low),
            1.0 if reached else -1.0,
        ]
        np.testing.assert_allclose(obs["view_history"], history.ravel(), atol=1e-5)
        assert obs["budget"][0] == pytest.approx(1.0 - used / budget)
        pose = obs["camera_pose"]
        if reached:
            # At the view's point on the sphere about the centre, looking at the centre.
            offset = radius * np.array(
                [
                    np.cos(elevation) * np.cos(azimuth),
                    np.cos(elevation) * np.sin(azimuth),
                    np.sin(elevation),
                ]
            )
            np.testing.assert_allclose(pose[:3], offset, atol=1e-4)
            np.testing.assert_allclose(pose[3:6], -offset / radius, atol=1e-4)
        else:
            np.testing.assert_array_equal(pose, before)  # the arm stayed
        np.testing.assert_allclose(pose, pose_of_camera(), atol=1e-6)
        # The image-up axis: a unit vector across the optical axis.
        assert np.linalg.norm(pose[6:]) == pytest.approx(1.0, abs=1e-5)
        assert pose[3:6] @ pose[6:] == pytest.approx(0.0, abs=1e-5)
    env.close()


def test_reward_coefficients_are_the_kwargs_and_reset_info_has_the_documented_keys():
    """Non-default coverage_reward_scale, motion_cost and refusal_penalty, on a reached and a
    refused view: catches a reward term that uses its DEFAULT_* constant instead of the
    kwarg, and a reset() info with keys the docstring does not list for it."""
    scale, cost, penalty = 3.0, 0.05, 0.7
    env = ViewPlanningEnv(
        coverage_reward_scale=scale, motion_cost=cost, refusal_penalty=penalty, **FAST
    )
    _, start = env.reset(seed=1)
    assert set(start) == RESET_INFO_KEYS
    assert start["coverage"] > 0 and start["coverage_gain"] == start["path_length"] == 0.0
    infos = []
    for view, refused in ((REACHED_VIEW, False), (REFUSED_VIEW, True)):
        _, reward, _, _, info = env.step(env.view_to_action(*view))
        infos.append(info)
        assert set(info) == RESET_INFO_KEYS | STEP_ONLY_INFO_KEYS
        assert info["refused"] == refused
        assert info["reward_coverage"] == pytest.approx(scale * info["coverage_gain"])
        assert info["reward_motion"] == pytest.approx(-cost * info["path_length"])
        assert info["reward_refusal"] == (-penalty if refused else 0.0)
        terms = info["reward_coverage"] + info["reward_motion"] + info["reward_refusal"]
        assert reward == pytest.approx(terms)
    assert infos[0]["coverage_gain"] > 0.1 and infos[0]["path_length"] > 0.1
    assert infos[1]["coverage_gain"] == infos[1]["path_length"] == 0.0
    assert sum(i["reward_coverage"] for i in infos) == pytest.approx(
        scale * (infos[-1]["coverage"] - start["coverage"])
    )
    env.close()


def test_user_meshes_load(tmp_path):
    import open3d as o3d

    mesh = o3d.geometry.TriangleMesh.create_box(0.3, 0.2, 0.1)
    path = tmp_path / "crate.stl"
    mesh.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(path), mesh)
    env = ViewPlanningEnv(objects=[str(path)], scales=(1.0,), coverage_samples=1024)
    _, info = env.reset(seed=0)
    assert info["object"] == "crate" and info["coverage"] > 0.1
    env.close()
    with pytest.raises(FileNotFoundError, match="missing.obj"):
        ViewPlanningEnv(objects=[str(tmp_path / "missing.obj")])


TETRAHEDRON_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def test_user_meshes_with_the_same_stem_are_named_by_their_paths(tmp_path):
    # ShapeNet names every model models/model_normalized.obj; a user's mug.obj meets "mug".
    paths = []
    for folder in ("chair1", "chair2"):
        (tmp_path / folder / "models").mkdir(parents=True)
        paths.append(tmp_path / folder / "models" / "model_normalized.obj")
        paths[-1].write_text(TETRAHEDRON_OBJ)
    (tmp_path / "mug.obj").write_text(TETRAHEDRON_OBJ)
    env = ViewPlanningEnv(
        objects=[*map(str, paths), "mug", str(tmp_path / "mug.obj")],
        scales=(1.0,),
        coverage_samples=256,
    )
    assert env.object_names == (
        "chair1/models/model_normalized.obj",
        "chair2/models/model_normalized.obj",
        "mug",
        "mug.obj",
    )
    _, info = env.reset(seed=0, options={"object": "chair2/models/model_normalized.obj"})
    assert info["object"] == "chair2/models/model_normalized.obj" and info["coverage"] > 0
    env.close()
    for twice in ([str(paths[0]), str(paths[0])], ["box", "box"]):
        with pytest.raises(ValueError, match="lists the same object more than once"):
            ViewPlanningEnv(objects=twice, scales=(1.0,), coverage_samples=256)


def test_an_object_no_taller_than_the_table_crop_is_refused(tmp_path):
    import open3d as o3d

    card = o3d.geometry.TriangleMesh.create_box(0.297, 0.210, 0.001)  # an A4 card, lying flat
    card.compute_triangle_normals()
    o3d.io.write_triangle_mesh(str(tmp_path / "card.stl"), card)
    with pytest.raises(ValueError, match=r"'card' stands 0.40 mm tall at scale 0.8.*cropped"):
        ViewPlanningEnv(objects=[str(tmp_path / "card.stl")], coverage_samples=256)
    env = ViewPlanningEnv(
        objects=[str(tmp_path / "card.stl")], scales=(1.0,), table_crop_height=0.0002
    )
    env.close()


def test_procedural_shapes_are_scanned_like_library_objects():
    names = ["procedural_3", "procedural_40", "box"]
    env = ViewPlanningEnv(objects=names, scales=(1.0,), coverage_samples=1024)
    env.action_space.seed(0)
    seen = set()
    for seed in range(6):
        obs, info = env.reset(seed=seed)
        seen.add(info["object"])
        obs, reward, _, _, info = env.step(env.action_space.sample())
        assert env.observation_space.contains(obs) and info["coverage"] > 0.1
    assert seen <= set(names) and len(seen) >= 2
    env.close()
    with pytest.raises(FileNotFoundError, match="procedural_<n>"):
        ViewPlanningEnv(objects=["procedural_03"])


@pytest.mark.slow
def test_the_procedural_set_is_its_64_shapes():
    from liuxing_envs.sim.objects import OBJECT_SETS

    env = ViewPlanningEnv(object_set="procedural", scales=(1.0,), coverage_samples=512)
    assert env.object_names == OBJECT_SETS["procedural"] and len(env.object_names) == 64
    _, info = env.reset(seed=0)
    assert info["object"].startswith("procedural_")
    env.close()


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"view_budget": 0}, "view_budget must be an integer in \\[1, 64\\]"),
        ({"action_mode": "joint"}, "action_mode='joint' is not allowed"),
        ({"object_set": "test"}, "object_set='test' is not allowed"),
        ({"motion": "teleport"}, "motion='teleport' is not allowed"),
        ({"radius_range": (0.5, 0.3)}, "radius_range must satisfy"),
        ({"azimuth_range_deg": "09"}, "azimuth_range_deg must be a pair of numbers"),
        ({"radius_range": (True, 0.5)}, "radius_range must be a pair of numbers"),
        ({"epsilon_fraction": -1.0}, "epsilon_fraction must be a number"),
        ({"objects": "box"}, "objects must be a non-empty list"),
        ({"objects": ["no_such_object"]}, "no_such_object"),
        ({"object_region": ((0.75, -0.35), (0.85, 0.35))}, "object_region must lie within x"),
        ({"object_region": ((0.0, 0.0), (0.1, 0.1))}, "object_region must lie within x"),
        # Too large for the workspace or the views: named with the scale, not an empty
        # interval for object_region or the observation radius alone.
        ({"objects": ["torus"], "scales": (5.0,)}, "'torus' at scale 5.0 reaches 0.360 m"),
        ({"objects": ["u_bracket"], "scales": (4.0,)}, "'u_bracket' at scale 4.0: observation"),
        ({"scales": {0.8: "a", 1.0: "b"}}, "scales must be a non-empty list"),  # was its keys
        # Two actions for one candidate view.
        ({"discrete_azimuths_deg": (0, 90, 360)}, "discrete_azimuths_deg must name distinct"),
        ({"discrete_elevations_deg": (30, 30)}, "discrete_elevations_deg must name distinct"),
        ({"discrete_elevations_deg": (30, 90)}, "below 90 \\(the top view is always a candidate"),
        # A switch takes a bool: 1 would be recorded in a run's config as given.
        ({"privileged": 1}, r"privileged=1 is not allowed; choose one of \[False, True\]"),
        ({"terminate_on_success": 1 + 0j}, r"terminate_on_success=\(1\+0j\) is not allowed"),
        ({"observe_free_space": np.True_}, r"observe_free_space=.*True.* is not allowed"),
        ({"filter_arm_points": np.float64(0.0)}, "filter_arm_points=.*0.0.* is not allowed"),
    ],
)
def test_bad_kwargs_fail_with_clear_messages(kwargs, message):
    with pytest.raises((ValueError, FileNotFoundError), match=message):
        ViewPlanningEnv(**kwargs)


def test_bad_actions_get_clear_errors_and_out_of_bounds_are_clipped(env):
    env.reset(seed=0)
    with pytest.raises(ValueError, match="must be finite"):
        env.step(np.array([np.nan, 0.0, 0.0], dtype=np.float32))
    with pytest.raises(ValueError, match="shape \\(3,\\)"):
        env.step(np.zeros(2, dtype=np.float32))
    _, _, _, _, clipped = env.step(np.array([0.0, 5.0, -5.0], dtype=np.float32))
    assert clipped["viewpoint"][1] == pytest.approx(90.0)  # elevation clipped to its maximum
    assert clipped["viewpoint"][2] == pytest.approx(0.30)  # radius clipped to its minimum
    with pytest.raises(ValueError, match="unknown reset option"):
        env.reset(options={"colour": "red"})


def test_step_before_reset_is_an_error():
    env = ViewPlanningEnv(**FAST)
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(env.action_space.sample())
    env.close()


def test_view_to_action_refuses_a_view_no_action_requests_unless_told_to_clip():
    """It clipped silently: a viewpoint logged in degrees (info["viewpoint"]) and passed back
    requested another view. Within the ranges it maps onto the action's [-1, 1] exactly."""
    env = ViewPlanningEnv(**FAST)
    low_az, low_el, low_r = env.azimuth_range[0], env.elevation_range[0], env.radius_range[0]
    high = (env.azimuth_range[1] - 2 * np.pi, env.elevation_range[1], env.radius_range[1])
    np.testing.assert_array_equal(env.view_to_action(low_az, low_el, low_r), [-1, -1, -1])
    np.testing.assert_array_equal(env.view_to_action(*high)[1:], [1, 1])
    middle = env.view_to_action(4 * np.pi, np.deg2rad(55.0), 0.375)  # two whole turns: 0 rad
    np.testing.assert_allclose(middle, [0.0, 0.0, 0.0], atol=1e-7)
    for view, shown in (
        ((90.0, 55.0, 0.375), "elevation 3151 deg"),  # degrees passed for radians
        ((0.0, 1.2, 5.0), "radius 5 m"),
        ((0.0, np.deg2rad(10.0), 0.35), "elevation 10 deg"),
    ):
        with pytest.raises(ValueError, match=f"{shown}.*outside the action's ranges"):
            env.view_to_action(*view)
    with pytest.raises(ValueError, match="finite"):
        env.view_to_action(0.0, np.nan, 0.35)
    clipped = env.view_to_action(0.0, np.deg2rad(10.0), 5.0, clip=True)
    np.testing.assert_array_equal(clipped[1:], [-1.0, 1.0])
    env.close()
    # A narrowed azimuth range: its start, logged in degrees and converted back a rounding
    # below it, is its start (it wrapped to almost a turn above and was refused), and
    # clipping takes the angularly nearer end.
    env = ViewPlanningEnv(azimuth_range_deg=(-114.0, -24.0), **FAST)
    start = np.radians(np.degrees(env.azimuth_range[0]))
    assert start < env.azimuth_range[0]
    assert env.view_to_action(start, np.deg2rad(55.0), 0.375)[0] == -1.0
    with pytest.raises(ValueError, match="azimuth 0 deg"):
        env.view_to_action(0.0, np.deg2rad(55.0), 0.375)
    for azimuth_deg, end in ((-120.0, -1.0), (-10.0, 1.0), (150.0, -1.0), (100.0, 1.0)):
        action = env.view_to_action(np.deg2rad(azimuth_deg), np.deg2rad(55.0), 0.375, clip=True)
        assert action[0] == end, azimuth_deg
    env.close()


def test_pickles_and_vectorises():
    env = ViewPlanningEnv(**FAST)
    env.reset(seed=4)
    clone = pickle.loads(pickle.dumps(env))
    action = env.view_to_action(np.pi / 2, np.pi / 4, 0.38)
    a, b = env.step(action), clone.step(action)
    np.testing.assert_array_equal(a[0]["depth"], b[0]["depth"])
    assert a[1] == b[1]
    env.close()
    clone.close()
    # This test process already holds OpenGL contexts, which a forked worker could not use
    # (it would fall back to ray casting); spawned workers start clean (see the README on
    # vector envs). The same seeds and actions give the same steps in both modes.
    actions = np.stack([action, env.view_to_action(-np.pi / 2, np.pi / 3, 0.4)])
    steps = {}
    for mode, vector_kwargs in (("sync", {}), ("async", {"context": "spawn"})):
        envs = gym.make_vec(
            ENV_ID, num_envs=2, vectorization_mode=mode, vector_kwargs=vector_kwargs, **FAST
        )
        obs, _ = envs.reset(seed=[0, 1])
        assert obs["depth"].shape == (2, 1, 64, 64)
        steps[mode] = envs.step(actions)
        assert steps[mode][1].shape == (2,)
        envs.close()
    for key in steps["sync"][0]:
        np.testing.assert_array_equal(steps["sync"][0][key], steps["async"][0][key])
    np.testing.assert_array_equal(steps["sync"][1], steps["async"][1])


def test_a_forked_worker_refuses_reconstruct_instead_of_hanging(monkeypatch):
    """open3d's OpenMP threads do not survive a fork: ``reconstruct()`` in the worker of an
    async vector env forked after the parent had imported open3d waited forever. It now
    raises, naming spawn; a spawned worker reconstructs."""
    # As when OMP_NUM_THREADS was not 1 at import (with it at 1 nothing would hang).
    monkeypatch.setattr(forking, "_single_openmp_thread", False)
    import open3d  # noqa: F401 (the package imports it only when first used)

    kwargs = {**FAST, "depth_backend": "raycast"}
    results = {}
    for context in ("fork", "spawn"):
        envs = gym.make_vec(
            ENV_ID,
            num_envs=1,
            vectorization_mode="async",
            vector_kwargs={"context": context},
            **kwargs,
        )
        try:
            envs.reset(seed=0)
            envs.call_async("reconstruct")
            try:
                results[context] = envs.call_wait(timeout=120)[0]
            except RuntimeError as error:
                results[context] = error
        finally:
            envs.close(terminate=True)
    assert isinstance(results["fork"], RuntimeError), results["fork"]
    message = str(results["fork"])
    assert "reconstruct() uses open3d" in message and "forked" in message
    assert "vector_kwargs={'context': 'spawn'}" in message
    reconstruction, metrics = results["spawn"]
    assert len(reconstruction.cloud.points) > 0 and 0.0 < metrics["fscore"] <= 1.0


def test_render_shows_the_scene_with_points_and_frustum():
    env = ViewPlanningEnv(render_mode="rgb_array", **FAST)
    env.reset(seed=0)
    env.step(env.view_to_action(np.pi / 2, np.pi / 4, 0.38))
    frame = env.render()
    assert frame.shape == (480, 640, 3) and frame.dtype == np.uint8
    green = (frame[..., 1] > 200) & (frame[..., 0] < 80) & (frame[..., 2] < 120)
    assert green.sum() > 20  # the fused points are drawn
    env.close()


def test_discrete_mode_offers_the_documented_candidates_and_rejects_others():
    env = ViewPlanningEnv(action_mode="discrete", **FAST)
    assert env.action_space.n == len(env.candidate_views) == 33
    assert env.candidate_views[-1][1] == pytest.approx(np.pi / 2)  # the top view comes last
    env.reset(seed=0)
    for bad in (33, -1, 2.5):
        with pytest.raises(ValueError, match="discrete action"):
            env.step(bad)
    _, _, _, _, info = env.step(32)
    assert info["viewpoint"][1] == pytest.approx(90.0)
    env.close()


def test_dynamic_motion_reaches_the_view_under_physics():
    env = ViewPlanningEnv(motion="dynamic", **FAST)
    env.reset(seed=3)
    _, _, _, _, info = env.step(env.view_to_action(np.pi / 2, np.pi / 4, 0.38))
    assert info["reachable"] and info["path_length"] > 0.5
    assert env.data.time > 0.5  # simulated time passed while the servos moved the arm
    position, rotation = env.camera.pose(env.data)
    to_center = env.center - position
    assert np.linalg.norm(to_center) == pytest.approx(0.38, abs=3e-3)
    optical_axis = -rotation[:, 2]
    assert optical_axis @ to_center / np.linalg.norm(to_center) > np.cos(np.deg2rad(1.0))
    env.close()


def test_a_dynamic_view_stopped_short_is_refused_but_imaged_where_the_arm_stopped():
    # A plan that is collision-free kinematically but whose servoed motion meets the cone.
    env = ViewPlanningEnv(objects=["cone"], scales=(1.0,), motion="dynamic")
    options = {"object": "cone", "scale": 1.0, "position": [0.47997, -0.01237], "yaw": 0.17794}
    env.reset(seed=0, options=options)
    for action in ([-0.1909, -0.6030, -0.8185], [0.1607, -0.4026, 0.3440]):
        obs, *_ = env.step(np.array(action, dtype=np.float32))
    before = env.arm.qpos
    after, reward, _, _, info = env.step(np.array([-0.6010, 0.8842, -0.2698], np.float32))
    assert info["reachable"] and info["refused"] and not info["sim_unstable"]
    assert reward == pytest.approx(sum(v for k, v in info.items() if k.startswith("reward_")))
    assert info["reward_refusal"] == -env.refusal_penalty
    assert np.linalg.norm(env.arm.qpos - before) > 0.5  # the arm moved, then stopped on contact
    # The image is the one the camera takes where it stopped, so depth and pose agree.
    expected = env.camera.render(env.data)
    scaled = np.round(np.clip(expected / env.depth_obs_range, 0, 1) * 255)
    np.testing.assert_allclose(after["depth"][0], scaled, atol=1)
    assert not np.array_equal(after["depth"], obs["depth"])
    assert env.observation_space.contains(after)
    env.close()


def test_previews_leave_a_dynamic_episode_unchanged():
    plain, previewed = (ViewPlanningEnv(motion="dynamic", **FAST) for _ in range(2))
    plain.reset(seed=4)
    previewed.reset(seed=4)
    for action in ([0.2, 0.1, 0.0], [-0.5, 0.6, 0.3], [0.7, -0.2, -0.4]):
        previewed.preview_view(0.5, 0.8, 0.35)
        previewed.preview_view(-2.0, 0.5, 0.42)
        first = plain.step(np.array(action, dtype=np.float32))
        second = previewed.step(np.array(action, dtype=np.float32))
        assert first[1] == second[1]
        np.testing.assert_array_equal(first[0]["depth"], second[0]["depth"])
        np.testing.assert_array_equal(plain.data.qvel, previewed.data.qvel)
    # A refused view leaves the arm where it was, so nothing recomputes its poses: they must
    # be the ones before the preview (which lag the state by an integration step), not a
    # recomputation from the state.
    previewed.preview_view(0.5, 0.8, 0.35)
    refused = plain.view_to_action(0.0, np.deg2rad(20), 0.45)
    first, second = plain.step(refused), previewed.step(refused)
    assert first[-1]["refused"] and second[-1]["refused"]
    for key in first[0]:
        np.testing.assert_array_equal(first[0][key], second[0][key])
    np.testing.assert_array_equal(plain.data.xpos, previewed.data.xpos)
    plain.close()
    previewed.close()


def test_view_history_stays_in_its_space_with_a_discrete_radius_outside_the_range():
    env = ViewPlanningEnv(action_mode="discrete", discrete_radius=0.6, **FAST)
    env.reset(seed=0)
    obs, *_ = env.step(0)
    assert obs["view_history"][3] == pytest.approx(1.0)  # the largest radius it can request
    assert env.observation_space.contains(obs)
    env.close()


def test_the_env_can_be_reset_after_close():
    env = ViewPlanningEnv(**FAST)
    first, _ = env.reset(seed=2)
    env.close()
    again, _ = env.reset(seed=2)
    np.testing.assert_array_equal(first["depth"], again["depth"])
    env.close()


def test_a_reset_position_outside_the_workspace_is_refused(env):
    with pytest.raises(ValueError, match=r"position \[0.84, 0.0\] puts box at scale 1.0"):
        env.reset(seed=0, options={"object": "box", "position": (0.84, 0.0)})
    _, info = env.reset(seed=0, options={"object": "box", "position": (0.6, 0.2)})
    assert info["object"] == "box"


def test_reset_options_position_and_yaw_place_the_object_there():
    """The ``position`` and ``yaw`` options are where the object stands, whatever the seed
    draws: catches either option being ignored for the drawn one. Checked on the placement
    and on MuJoCo's own pose of the object's body."""
    env = ViewPlanningEnv(**FAST)
    options = {"object": "box", "position": (0.6, 0.2), "yaw": 0.3}
    body = env.model.body("object_box_x1.0").id
    for seed in (0, 1):
        _, info = env.reset(seed=seed, options=options)
        assert info["object"] == "box" and info["coverage"] > 0  # the start view sees it
        np.testing.assert_allclose(env.placed.position, [0.6, 0.2, 0.0])
        assert env.placed.yaw == pytest.approx(0.3)
        np.testing.assert_allclose(env.data.xpos[body], [0.6, 0.2, 0.0], atol=1e-12)
        np.testing.assert_allclose(
            env.data.xquat[body], [np.cos(0.15), 0.0, 0.0, np.sin(0.15)], atol=1e-12
        )
        # The estimated centre comes from the depth image: the box is seen where it was put.
        np.testing.assert_allclose(env.center[:2], [0.6, 0.2], atol=0.02)
    env.close()


def test_reset_options_are_checked_whatever_the_draw_and_a_refusal_changes_nothing():
    env = ViewPlanningEnv(objects=["box", "mug"], scales=(0.9, 1.1), coverage_samples=2048)
    # numpy compares float32 with float in float32: the option must become the scale itself.
    _, info = env.reset(seed=0, options={"object": "box", "scale": np.float32(0.9)})
    assert info["scale"] == 0.9
    one = ViewPlanningEnv(**FAST)  # True equals the scale 1.0, but is no scale
    with pytest.raises(ValueError, match=r"reset option scale=True is not one of \(1.0,\)"):
        one.reset(seed=0, options={"scale": True})
    one.close()
    # x = 0.23 m leaves the mug at either scale and the box at 0.9 inside the crop, not the
    # box at 1.1: refused at every seed unless the options rule that one out.
    for seed in range(4):
        with pytest.raises(ValueError, match="puts box at scale 1.1 partly outside"):
            env.reset(seed=seed, options={"position": (0.23, 0.0)})
    _, info = env.reset(seed=0, options={"object": "mug", "position": (0.23, 0.0)})
    assert info["object"] == "mug"

    env.reset(seed=3)
    expected, _ = env.reset()  # the episode the generator seeded with 3 draws next
    env.reset(seed=3)
    with pytest.raises(ValueError, match="partly outside"):
        env.reset(seed=7, options={"object": "box", "scale": 1.1, "position": (0.23, 0.0)})
    drawn, _ = env.reset()
    np.testing.assert_array_equal(drawn["depth"], expected["depth"])  # same pose
    env.close()


def test_preview_view_names_a_bad_view(env):
    env.reset(seed=0)
    for view in ((np.nan, 0.5, 0.38), (0.0, np.inf, 0.38), (0.0, 0.5, -0.38), (0.0, 0.5, "0.38")):
        with pytest.raises(ValueError, match="preview_view needs a finite azimuth and elevation"):
            env.unwrapped.preview_view(*view)


def test_reconstruct_names_a_bad_tau_fraction(env):
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"tau_fraction must be a number in \[0.0001, 1.0\]"):
        env.unwrapped.reconstruct(tau_fraction=-1)


def test_noisy_depth_is_seeded():
    from liuxing_envs.sim.camera import DepthNoise

    env = ViewPlanningEnv(depth_noise=DepthNoise.realsense_like(), **FAST)
    first, _ = env.reset(seed=8)
    second, _ = env.reset(seed=8)
    third, _ = env.reset(seed=9)
    np.testing.assert_array_equal(first["depth"], second["depth"])
    assert not np.array_equal(first["depth"], third["depth"])
    env.close()


def test_depth_noise_can_be_given_as_a_config_gives_it():
    """train.py's --env-kwargs and YAML give a mapping or a name, not a DepthNoise."""
    from liuxing_envs.sim.camera import DepthNoise

    named = ViewPlanningEnv(depth_noise="realsense", **FAST)
    mapped = ViewPlanningEnv(depth_noise={"sigma_base": 0.002, "dropout_prob": 0.1}, **FAST)
    assert named.settings.sensor.depth_noise == DepthNoise.realsense_like()
    assert mapped.settings.sensor.depth_noise == DepthNoise(sigma_base=0.002, dropout_prob=0.1)
    plain = ViewPlanningEnv(**FAST)
    clean, _ = plain.reset(seed=3)
    noisy, _ = mapped.reset(seed=3)
    assert (noisy["depth"] != clean["depth"]).mean() > 0.1
    for env in (named, mapped, plain):
        env.close()
    with pytest.raises(ValueError, match="depth_noise has no setting 'sigma'; its settings are"):
        ViewPlanningEnv(depth_noise={"sigma": 0.01}, **FAST)
    with pytest.raises(ValueError, match="depth_noise must be a DepthNoise, None, 'realsense'"):
        ViewPlanningEnv(depth_noise="kinect", **FAST)


def test_ground_truth_only_in_the_privileged_observation():
    plain = ViewPlanningEnv(**FAST)
    obs, _ = plain.reset(seed=0)
    assert "coverage" not in obs
    privileged = ViewPlanningEnv(privileged=True, **FAST)
    obs, info = privileged.reset(seed=0)
    assert obs["coverage"][0] == pytest.approx(info["coverage"])
    plain.close()
    privileged.close()


def test_free_space_tells_seen_empty_cells_from_unseen_ones():
    plain = ViewPlanningEnv(**FAST)
    assert "free_space" not in plain.reset(seed=0)[0]
    plain.close()
    env = ViewPlanningEnv(observe_free_space=True, **FAST)
    obs, _ = env.reset(seed=0, options={"object": "box", "yaw": 0.0})
    assert env.observation_space.contains(obs)
    grid = env.map_grid
    occupied = obs["map"].reshape((grid,) * 3).astype(bool)
    free = obs["free_space"].reshape((grid,) * 3).astype(bool)
    assert not (occupied & free).any()
    # The start view looks down on the box: in the column through its top, the cells just
    # above the top are free, the box's inside below it is not (unseen).
    x, y = np.argwhere(occupied.any(axis=2)).mean(axis=0).round().astype(int)
    top = np.flatnonzero(occupied[x, y]).max()
    assert free[x, y, top + 1 : top + 4].all()
    assert not free[x, y, :top].any()
    # Rays to the table carve too: most of the layer just above the table top is seen empty.
    cell = env.map_extent / grid
    layer = int((0.015 - (env.center[2] - env.map_extent / 2)) / cell)
    assert free[:, :, layer][~occupied.any(axis=2)].mean() > 0.4
    # A side view sees more empty space, and what it sees stays free or turns occupied.
    obs, *_ = env.step(np.array([0.0, -0.8, -0.5], dtype=np.float32))
    free_after = obs["free_space"].reshape((grid,) * 3).astype(bool)
    occupied_after = obs["map"].reshape((grid,) * 3).astype(bool)
    assert free_after.sum() > free.sum()
    assert (free_after | occupied_after)[free].all()
    # Nothing carries over into the next episode.
    fresh = ViewPlanningEnv(observe_free_space=True, **FAST)
    np.testing.assert_array_equal(
        env.reset(seed=5)[0]["free_space"], fresh.reset(seed=5)[0]["free_space"]
    )
    fresh.close()
    env.close()


def test_held_out_set_holds_only_held_out_objects():
    from liuxing_envs.sim.objects import OBJECT_SETS

    env = ViewPlanningEnv(object_set="held_out", scales=(1.0,), coverage_samples=1024)
    assert set(env.object_names) == set(OBJECT_SETS["held_out"])
    assert not set(env.object_names) & set(OBJECT_SETS["train"])
    env.close()


@pytest.mark.slow
def test_reconstruction_of_a_four_view_scan_is_scored_and_saved(tmp_path):
    env = ViewPlanningEnv(objects=["mug"], scales=(1.0,), coverage_samples=4096)
    run_episode(env, FourViewpointBaseline(env), seed=0)
    record, metrics = env.reconstruct(save_dir=tmp_path, poisson_depth=7)
    assert record.has_mesh
    assert metrics["chamfer"] < 0.01  # metres
    assert 0.0 <= metrics["fscore"] <= 1.0 and metrics["precision"] > 0.5
    assert {p.suffix for p in tmp_path.iterdir()} >= {".ply", ".pcd"}
    # The views are the episode's: a caller's own are refused by name (was a TypeError of
    # "multiple values"), as is a keyword open3d would crash on.
    with pytest.raises(TypeError, match="camera locations from the episode"):
        env.reconstruct(camera_locations=[[0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="normal_max_nn"):
        env.reconstruct(normal_max_nn=0)
    env.close()


@pytest.mark.parametrize("motion", ["kinematic", "dynamic"])
def test_ray_cast_stand_in_scene_gives_the_live_models_image(motion):
    # The raycast backend casts in a per-variant copy of the scene without the parked
    # variants (faster); the image must be the one the full live model gives, bit for bit.
    env = ViewPlanningEnv(depth_backend="raycast", motion=motion, **FAST)
    env.action_space.seed(0)
    for seed in range(3):
        env.reset(seed=seed)
        for _ in range(2):
            env.step(env.action_space.sample())
            np.testing.assert_array_equal(env.depth, env.camera.render(env.data))
    env.close()


def test_embree_backend_sees_what_the_raycast_backend_sees():
    # Embree (float32) casts the rays against the object's mesh; MuJoCo casts the rest. Same
    # pixels with a return, depths within micrometres, so the same fused map and coverage.
    episodes = {}
    for backend in ("raycast", "embree"):
        env = ViewPlanningEnv(depth_backend=backend, objects=["mug", "bowl", "l_bracket"])
        env.action_space.seed(0)
        images, coverages = [], []
        for seed in range(6):
            env.reset(seed=seed)
            images.append(env.depth.copy())
            for _ in range(4):
                _, _, _, _, info = env.step(env.action_space.sample())
                images.append(env.depth.copy())
                coverages.append(info["coverage"])
        episodes[backend] = (np.array(images), np.array(coverages))
        if backend == "embree":
            assert env.camera.active_backend.meshes_in_embree  # the object went through Embree
        env.close()
    (cast, cast_coverage), (embree, embree_coverage) = episodes["raycast"], episodes["embree"]
    np.testing.assert_array_equal(cast > 0, embree > 0)
    assert (cast > 0).mean() > 0.5
    np.testing.assert_allclose(embree, cast, rtol=0, atol=2e-5)
    assert not np.array_equal(embree, cast)  # float32 hits: Embree really cast them
    np.testing.assert_array_equal(embree_coverage, cast_coverage)


def test_collision_checks_in_the_stand_in_scene_match_the_live_model():
    # The arm plans in a per-variant copy of the scene (faster kinematics); every path check
    # and IK collision verdict must be the one the full live model gives.
    env = ViewPlanningEnv(objects=["bowl", "table"], scales=(1.0, 1.4))
    rng = np.random.default_rng(0)
    hits = {"free": 0, "object": 0}
    for seed in range(4):
        env.reset(seed=seed)
        start, object_geom = env.arm.qpos, f"object_{env.placed.name}"
        for _ in range(20):
            # Camera poses looking down from inside and above the object (whose collision
            # shape is its convex hull): some paths end inside it, some are free.
            eye = env.placed.position + rng.uniform([-0.03, -0.03, 0.03], [0.03, 0.03, 0.4])
            rotation = look_at(eye, eye - [0.0, 0.0, 1.0], up=[1.0, 0.0, 0.0])
            goal = env.arm.solve_ik(eye, rotation, roll_free=True, check_collisions=False).qpos
            in_stand_in = env.arm.check_path(start, goal)
            stand_in_contacts = env.arm.collisions(goal)
            env.arm.use_collision_scene(None)
            live = env.arm.check_path(start, goal)
            assert in_stand_in.free == live.free
            assert in_stand_in.fraction == live.fraction
            np.testing.assert_array_equal(in_stand_in.last_free_qpos, live.last_free_qpos)
            assert set(stand_in_contacts) == set(env.arm.collisions(goal))
            hits["free"] += live.free
            hits["object"] += any(object_geom in (c.geom1 + c.geom2) for c in live.contacts)
            scenes = env.scene.stand_ins(env.placed.name, env.placed.scale)
            env.arm.use_collision_scene(*scenes.collision_scene(env.placed))
    assert min(hits.values()) >= 5, hits  # free paths and paths into the object were both tried
    env.close()


def test_envs_of_one_process_share_stand_ins_without_disturbing_each_other():
    # The stand-in models are shared by the envs of a process (a vectorised env saves 0.3 GB
    # per env with the procedural shapes); making another env must not hide the object from
    # the first env's collision checks or images mid-episode.
    options = {"object": "table", "position": (0.45, 0.0), "yaw": 0.0}
    first = ViewPlanningEnv(objects=["box", "table"], scales=(1.0,), depth_backend="raycast")
    first.reset(seed=0, options=options)
    eye = np.array([0.45, 0.0, 0.06])  # inside the table-shaped object's convex hull
    rotation = look_at(eye, eye - [0.0, 0.0, 1.0], up=[1.0, 0.0, 0.0])
    inside = first.arm.solve_ik(eye, rotation, roll_free=True, check_collisions=False).qpos
    image = first.scene.render_depth(None)
    second = ViewPlanningEnv(objects=["box", "table"], scales=(1.0,), depth_backend="raycast")
    second.reset(seed=1, options={**options, "object": "box", "position": (0.6, 0.25)})
    key = ("table", 1.0)
    assert first.scene.stand_ins(*key).model is second.scene.stand_ins(*key).model
    assert any("object_table" in c.geom1 + c.geom2 for c in first.arm.collisions(inside))
    np.testing.assert_array_equal(first.scene.render_depth(None), image)
    first.close()
    second.close()


def test_a_shared_stand_in_lives_as_long_as_an_env_uses_it():
    # A process that makes envs for one large user mesh after another must not keep every
    # mesh's stand-ins: a shared model goes with the last env holding it.
    # A shape no other test uses: an env of another test may still hold a library object's.
    key = ("procedural_4321", 1.0)
    first = ViewPlanningEnv(objects=["procedural_4321"], scales=(1.0,))
    model = weakref.ref(first.scene.stand_ins(*key).model)
    second = ViewPlanningEnv(objects=["procedural_4321"], scales=(1.0,))
    assert second.scene.stand_ins(*key).model is model()
    second.reset(seed=0)
    first.close()
    del first
    gc.collect()
    assert model() is not None
    second.close()
    del second
    gc.collect()
    assert model() is None


def test_the_arm_collides_with_the_placed_object_and_not_with_parked_ones():
    # Regression: MuJoCo's broad phase filters on the compiled body_contype, so turning on
    # only the geom's contype left the object ghostly and the arm could plan through it.
    env = ViewPlanningEnv(objects=["box", "table"], scales=(1.0,))
    options = {"object": "table", "position": (0.45, 0.0), "yaw": 0.0}
    env.reset(seed=0, options=options)
    eye = np.array([0.45, 0.0, 0.06])  # inside the table-shaped object's convex hull
    rotation = look_at(eye, eye - [0.0, 0.0, 1.0], up=[1.0, 0.0, 0.0])
    inside = env.arm.solve_ik(eye, rotation, roll_free=True, check_collisions=False)
    assert inside.success
    for scene in ("stand-in", "live"):
        contacts = env.arm.collisions(inside.qpos)
        assert any("object_table" in c.geom1 + c.geom2 for c in contacts), scene
        assert not env.arm.check_path(env.arm.qpos, inside.qpos).free, scene
        env.arm.use_collision_scene(None)
    # The next episode parks the table: the same configuration is free in both scenes.
    env.reset(seed=0, options={**options, "object": "box", "position": (0.6, 0.25)})
    for scene in ("stand-in", "live"):
        assert not env.arm.collisions(inside.qpos), scene
        env.arm.use_collision_scene(None)
    env.close()


@pytest.mark.parametrize("crop", [0.02, 0.05])
def test_a_high_table_crop_leaves_full_coverage_reachable(crop):
    # Points below the crop are never fused, so samples more than epsilon below it can never
    # be covered: they must not count, or seeing every point above the crop capped coverage
    # at 0.82 (20 mm) and 0.47 (50 mm) on this box.
    from liuxing_envs.sim.objects import surface_samples

    env = ViewPlanningEnv(objects=["box"], scales=(1.0,), table_crop_height=crop)
    env.reset(seed=0)
    tracker = env.coverage
    assert (tracker.samples[tracker.observable][:, 2] >= crop - tracker.epsilon).all()
    dense, _ = surface_samples("box", 100_000, 1)
    seen = dense[dense[:, 2] >= crop]  # every point of the surface a scan could fuse
    tracker.update(seen)
    assert tracker.coverage > 0.99
    env.close()


def test_the_default_table_crop_leaves_every_observable_sample_counted():
    from liuxing_envs.sim.objects import observable_samples

    env = ViewPlanningEnv(**FAST)
    env.reset(seed=0)
    truth = observable_samples(env.placed.name, env.placed.scale, env.coverage_samples)
    np.testing.assert_array_equal(env.coverage.observable, truth.observable)
    env.close()


def test_coverage_counts_what_the_envs_own_view_space_sees():
    """The observable samples are those a view of this env's view space sees: a narrower
    elevation and radius range counts fewer of a T-pipe's (its lower flanks), and exactly
    those observable_samples finds on that space, less the ones under the table crop."""
    from liuxing_envs.sim.objects import observable_samples

    kwargs = {"objects": ["t_pipe"], "scales": (1.0,), "coverage_samples": 2048}
    wide = ViewPlanningEnv(**kwargs)
    narrow = ViewPlanningEnv(**kwargs, elevation_range_deg=(60, 90), radius_range=(0.35, 0.45))
    for env in (wide, narrow):
        env.reset(seed=0)
    truth = observable_samples(
        "t_pipe", 1.0, 2048, radii=(0.35, 0.45), elevations_deg=(60.0, 67.5, 75.0, 82.5, 90.0)
    )
    tracker = narrow.coverage
    above_crop = tracker.samples[:, 2] >= narrow.table_crop_height - tracker.epsilon
    np.testing.assert_array_equal(tracker.observable, truth.observable & above_crop)
    assert not (tracker.observable & ~wide.coverage.observable).any()
    # The env's defaults are observable_samples' own.
    default_truth = observable_samples("t_pipe", 1.0, 2048).observable
    np.testing.assert_array_equal(wide.coverage.observable, default_truth & above_crop)
    assert tracker.observable.mean() < wide.coverage.observable.mean() - 0.05
    # Discrete actions: the candidates' elevations at their radius, and the top view.
    discrete = ViewPlanningEnv(**kwargs, action_mode="discrete", discrete_elevations_deg=(30, 50))
    discrete.reset(seed=0)
    candidates = observable_samples(
        "t_pipe", 1.0, 2048, radii=(V1.action.discrete_radius,), elevations_deg=(30, 50, 90)
    )
    np.testing.assert_array_equal(discrete.coverage.observable, candidates.observable & above_crop)
    for env in (wide, narrow, discrete):
        env.close()


_NO_GL_SCRIPT = """
import json, warnings
from liuxing_envs.envs.view_planning import ViewPlanningEnv
outcomes = []
for kwargs in ({"depth_backend": "gl"}, {"render_mode": "rgb_array"}, {}):
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # auto: OpenGL missing, ray-cast instead
            env = ViewPlanningEnv(objects=["box"], scales=(1.0,), coverage_samples=256, **kwargs)
            env.reset(seed=0)
        outcomes.append(env.camera.backend)
    except ValueError as error:
        outcomes.append(str(error))
print(json.dumps(outcomes))
"""


def test_settings_that_render_are_refused_when_made_without_opengl():
    # MUJOCO_GL is read when mujoco is imported: a fresh interpreter. They used to fail at
    # the first image with an AttributeError naming no setting.
    gl_depth, render, auto = outcomes_without_opengl(_NO_GL_SCRIPT)
    assert gl_depth.startswith("depth_backend='gl' needs OpenGL"), gl_depth
    assert render.startswith("render_mode='rgb_array' needs OpenGL"), render
    assert auto == "raycast"
