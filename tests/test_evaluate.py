"""evaluate.py and its report: paired episodes, honest statistics, clean failures.

End-to-end tests run ``evaluate.py`` as a subprocess on the shipped ViewPlanning policy and on
a tiny SAC run trained here (with observation normalisation), for a few episodes each."""

from __future__ import annotations

import hashlib
import json
import math
import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml

from agents import run_folder
from agents.statistics import (
    bootstrap_ci,
    interval_text,
    iqm,
    probability_of_improvement,
    run_bootstrap_ci,
    stratified_bootstrap_ci,
    wilson_interval,
)
from tests.scripts import REPO, run_main, run_script

SHIPPED_VIEW_POLICY = REPO / "policies" / "ViewPlanning-v1" / "ppo"


@pytest.fixture(scope="module")
def grasp_run(tmp_path_factory) -> Path:
    """A tiny SAC run on InstrumentGrasp-v1 (normalised observations, as its YAML asks)."""
    from tests.test_train import QUICK_HYPERPARAMS, run_train

    run_dir = tmp_path_factory.mktemp("runs") / "grasp_sac"
    run_train(
        *("--env", "InstrumentGrasp-v1", "--algo", "sac", "-n", "256"),
        *("--run-dir", str(run_dir), "--eval-freq", "128", "--save-freq", "128"),
        *("--eval-episodes", "1", "--final-episodes", "0", "--no-progress-bar"),
        *("--hyperparams", *QUICK_HYPERPARAMS[("InstrumentGrasp-v1", "sac")]),
        # The opening-commanded gripper and the stiff arm: the baselines are scored with the
        # run's env kwargs, and squeezing trips the hard limit only with these.
        *("--env-kwargs", "gripper_control=opening", "approach_guard_fingers=false"),
        *("arm_stiffness=1.0", "max_translation=0.02", "max_yaw=0.2"),
    )
    return run_dir


def run_evaluate(*args: str, check: bool = True):
    """evaluate.py with ``args``, in this process (see :func:`tests.scripts.run_main`)."""
    import evaluate

    return run_main(evaluate.main, "evaluate.py", args, check=check)


def read_report(out: Path) -> dict:
    assert (out / "report.md").is_file()
    return json.loads((out / "report.json").read_text())


def assert_ci_holds_mean(entry: dict, key: str = "mean") -> None:
    low, high = entry["ci95"]
    assert low - 1e-9 <= entry[key] <= high + 1e-9, entry


# --- statistics -----------------------------------------------------------------------------


@pytest.mark.parametrize("trials", [2, 50, 100, 1000])
def test_wilson_interval_holds_the_rate_exactly_at_zero_and_one(trials):
    assert wilson_interval(trials, trials)[1] == 1.0
    assert wilson_interval(0, trials)[0] == 0.0
    low, high = wilson_interval(trials // 2, trials)
    assert 0.0 < low < 0.5 < high < 1.0


def test_one_value_has_no_bootstrap_interval_and_reports_say_so():
    # Every resample of one value is that value: a zero-width interval would claim certainty.
    assert bootstrap_ci([0.7]) is None
    low, high = bootstrap_ci([0.6, 0.8, 0.7])
    assert 0.6 - 1e-9 <= low < 0.7 < high <= 0.8 + 1e-9
    assert interval_text(None) == "[no interval from one value]"
    assert interval_text((0.01, 0.02), scale=1000, digits=1) == "[10.0, 20.0]"


def test_a_wilson_interval_of_impossible_counts_is_refused():
    for successes, trials in ((3, 2), (-1, 5)):
        with pytest.raises(ValueError, match=f"got {successes} of {trials}"):
            wilson_interval(successes, trials)


def test_iqm_is_the_mean_of_the_middle_half():
    assert iqm([0, 1, 2, 3, 4, 5, 6, 100]) == pytest.approx(np.mean([2, 3, 4, 5]))
    assert iqm([[1.0, 1.0], [1.0, 1.0]]) == 1.0


def test_a_nan_score_gives_nan_aggregates_not_a_number_that_hides_it():
    # Sorted last, a NaN used to be trimmed out of the IQM, and it counted as a loss in P(X > Y).
    assert math.isnan(iqm([1.0, math.nan, 2.0, 3.0]))
    with_nan = np.array([[0.9, math.nan], [0.8, 0.7]])
    assert math.isnan(probability_of_improvement(with_nan, np.array([[0.5, 0.5]])))
    assert math.isnan(probability_of_improvement(np.array([[0.5, 0.5]]), with_nan))


def test_stratified_bootstrap_resamples_runs_within_each_task():
    identical_runs = np.tile(np.linspace(0, 1, 10), (3, 1))
    assert stratified_bootstrap_ci(identical_runs, np.mean) == pytest.approx((0.5, 0.5))
    rng = np.random.default_rng(0)
    noisy = rng.normal(0.5, 0.1, size=(5, 20))
    low, high = stratified_bootstrap_ci(noisy, iqm)
    assert low < iqm(noisy) < high
    assert high - low < 0.2


def test_the_seed_bootstrap_resamples_whole_seeds_and_keeps_their_spread():
    # Six seeds, each a fixed offset on every one of 100 episodes: the spread a new set of
    # seeds would show. Mixing seeds within each episode (stratified) averages it away.
    rng = np.random.default_rng(1)
    episodes = rng.normal(0.85, 0.05, size=100)
    offsets = np.array([-0.012, -0.006, -0.002, 0.003, 0.007, 0.010])
    scores = offsets[:, None] + episodes[None, :]
    low, high = run_bootstrap_ci(scores, np.mean)
    assert (low, high) == pytest.approx(bootstrap_ci(scores.mean(axis=1)))  # the same resamples
    stratified_low, stratified_high = stratified_bootstrap_ci(scores, np.mean)
    assert high - low > 2 * (stratified_high - stratified_low)
    assert run_bootstrap_ci(scores[:1], np.mean) is None


def test_probability_of_improvement_counts_wins_and_half_ties():
    better = np.array([[2.0, 2.0, 2.0]])
    worse = np.array([[1.0, 1.0, 1.0]])
    assert probability_of_improvement(better, worse) == 1.0
    assert probability_of_improvement(worse, better) == 0.0
    assert probability_of_improvement(better, better) == 0.5
    # Task 0: one run wins (1), one ties (1/2): 0.75. Task 1: both tie: 0.5. Mean: 0.625.
    two_seeds = np.array([[2.0, 0.0], [0.0, 0.0]])
    assert probability_of_improvement(two_seeds, np.zeros((1, 2))) == pytest.approx(0.625)


# --- end to end -------------------------------------------------------------------------------


@pytest.mark.slow
def test_view_planning_report_is_paired_and_its_numbers_are_sound(tmp_path):
    out = tmp_path / "report"
    result = run_evaluate(
        str(SHIPPED_VIEW_POLICY),
        *("--baselines", "four-view,uniform,greedy-oracle", "--episodes", "3"),
        *("--reconstruct-episodes", "1", "--save-reconstructions", "1", "--out", str(out)),
        *("--video", "--video-episodes", "1"),
    )
    assert "four-view" in result.stdout
    for label in ("ppo", "four-view", "uniform", "greedy-oracle"):
        assert (out / "videos" / f"{label}.mp4").stat().st_size > 10_000
    report = read_report(out)
    section = report["environments"]["ViewPlanning-v1"]
    labels = [c["label"] for c in section["contestants"]]
    assert labels == ["ppo", "four-view", "uniform", "greedy-oracle"]
    assert section["paired"]
    scenes = [
        [
            (e["seed"], e["object"], e["scale"], tuple(e["position"]), e["yaw"])
            for e in c["episodes"]
        ]
        for c in section["contestants"]
    ]
    assert all(scene == scenes[0] for scene in scenes)
    assert [seed for seed, *_ in scenes[0]] == [1_000_000, 1_000_001, 1_000_002]
    for contestant in section["contestants"]:
        summary = contestant["summary"]
        assert 0.0 <= summary["mean"] <= 1.0
        assert "mean_yaw" not in summary  # the object's yaw, an angle: no mean
        assert_ci_holds_mean(summary)
        for episode in contestant["episodes"]:
            curve = episode["coverage_after_view"]
            assert len(curve) == 5  # the start view and a budget of four
            assert np.all(np.diff(curve) >= 0), "coverage never falls"
            assert curve[-1] == pytest.approx(episode["coverage"])
            reached = episode["views_to_90"]
            assert (reached is None) == (max(curve) < 0.9)
        for entry in summary["coverage_after_view"]:
            assert_ci_holds_mean(entry)
        # The first episode was reconstructed and scored; the others were not.
        assert "fscore" in contestant["episodes"][0] and "fscore" not in contestant["episodes"][1]
        assert 0.0 <= summary["fscore"]["mean"] <= 1.0 and summary["chamfer"]["mean"] > 0
    # The start view is the same for everyone; the privileged oracle ends highest.
    starts = {c["summary"]["coverage_after_view"][0]["mean"] for c in section["contestants"]}
    assert len(starts) == 1
    oracle = section["contestants"][-1]["summary"]["mean"]
    assert oracle >= max(c["summary"]["mean"] for c in section["contestants"][:-1])
    saved = out / "reconstructions" / "ppo" / "seed_1000000"
    assert (saved / "ground_truth.ply").is_file() and (saved / "reconstruction_cloud.ply").is_file()
    for figure in ("coverage_vs_views.png", "reconstructions/ppo/reconstructions.png"):
        assert (out / figure).stat().st_size > 10_000
    markdown = (out / "report.md").read_text()
    assert "| ppo | trained |" in markdown and "greedy-oracle | privileged" in markdown


@pytest.mark.slow
def test_grasp_report_matches_force_traces_and_writes_a_video(grasp_run, tmp_path):
    out = tmp_path / "report"
    run_evaluate(
        str(grasp_run),
        *("--baselines", "scripted-grasp,squeeze", "--episodes", "2", "--out", str(out)),
        *("--instrument-set", "train"),
    )
    report = read_report(out)
    section = report["environments"]["InstrumentGrasp-v1"]
    assert section["paired"]
    by_label = {c["label"]: c for c in section["contestants"]}
    assert set(by_label) == {"grasp_sac", "scripted-grasp", "squeeze"}
    assert by_label["grasp_sac"]["env_kwargs"]["instrument_set"] == "train"
    assert by_label["grasp_sac"]["model_file"] == str(grasp_run / "best_model.zip")
    assert by_label["squeeze"]["model_file"] is None
    scored = (grasp_run / "best_model.zip").read_bytes()
    assert by_label["grasp_sac"]["model_sha256"] == hashlib.sha256(scored).hexdigest()
    assert by_label["squeeze"]["model_sha256"] is None
    assert "grasp_sac** (trained, seed 0): `" in (out / "report.md").read_text()
    assert "(scored: `best_model.zip`)" in (out / "report.md").read_text()
    for contestant in section["contestants"]:
        summary = contestant["summary"]
        assert_ci_holds_mean(summary["success"], "rate")
        # The start's yaw pairs episodes; an angle's arithmetic mean is no figure.
        assert "mean_start_yaw" not in summary and "mean_max_lift" in summary
        for episode in contestant["episodes"]:
            assert len(episode["force_trace"]) == episode["length"]
            assert episode["peak_force"] == pytest.approx(max(episode["force_trace"]), abs=1e-3)
            assert episode["hard_limit_exceeded"] == (max(episode["force_trace"]) > 15.0)
    # Squeezing trips the hard limit; the gentle script lifts without going over the limit.
    assert by_label["squeeze"]["summary"]["hard_limit_exceeded"]["rate"] == 1.0
    assert by_label["squeeze"]["summary"]["over_force_limit"]["count"] == 2  # a count, not 0
    scripted = by_label["scripted-grasp"]["summary"]
    assert scripted["success"]["rate"] == 1.0 and scripted["over_force_limit"]["count"] == 0
    assert scripted["max_lift"]["mean"] >= 0.10
    for figure in ("force_traces.png", "grasp_outcomes.png", "peak_forces.png"):
        assert (out / figure).stat().st_size > 10_000


def test_a_grasp_video_shows_every_step_of_its_episodes(tmp_path):
    import cv2

    from agents.contestants import baseline_contestant
    from agents.video import record_videos

    scripted = baseline_contestant("scripted-grasp", "InstrumentGrasp-v1", {"episode_steps": 12})
    (path,) = record_videos([scripted], seeds=[0, 1], out=tmp_path)
    assert path == tmp_path / "videos" / "scripted-grasp.mp4"
    video = cv2.VideoCapture(str(path))
    frames = int(video.get(cv2.CAP_PROP_FRAME_COUNT))
    video.release()
    assert frames == 2 * (12 + 1)  # each episode's start and its steps


@pytest.mark.slow
def test_several_seeds_are_aggregated_with_probability_of_improvement(tmp_path):
    runs = []
    for seed in (2, 3):
        run = tmp_path / f"ppo_seed{seed}"
        shutil.copytree(SHIPPED_VIEW_POLICY, run)
        config = run / run_folder.CONFIG
        config.write_text(re.sub(r"(?m)^seed: \d+$", f"seed: {seed}", config.read_text(), count=1))
        runs.append(str(run))
    out = tmp_path / "report"
    run_evaluate(
        *runs,
        *("--baselines", "four-view", "--episodes", "2", "--reconstruct-episodes", "0"),
        *("--out", str(out)),
    )
    section = read_report(out)["environments"]["ViewPlanning-v1"]
    (aggregate,) = section["aggregates"]
    assert aggregate["group"] == "ppo" and len(aggregate["runs"]) == 2
    finals = [e["coverage"] for c in section["contestants"][:2] for e in c["episodes"]]
    assert min(finals) <= aggregate["iqm"] <= max(finals)
    assert_ci_holds_mean({"mean": aggregate["iqm"], "ci95": aggregate["iqm_ci95"]})
    assert_ci_holds_mean({"mean": aggregate["mean"], "ci95": aggregate["mean_seed_ci95"]})
    improvement = aggregate["probability_of_improvement"]
    assert improvement["over"] == "four-view" and 0.0 <= improvement["value"] <= 1.0
    policy = [e["coverage"] for e in section["contestants"][0]["episodes"]]
    baseline = [e["coverage"] for e in section["contestants"][2]["episodes"]]
    expected = np.mean(
        [1.0 if p > b else 0.5 if p == b else 0.0 for p, b in zip(policy, baseline, strict=True)]
    )
    assert improvement["value"] == pytest.approx(expected)

    # A copy of a run is not a second training seed (the same path twice is refused).
    twin = tmp_path / "twin"
    shutil.copytree(runs[0], twin)
    again = tmp_path / "again"
    run_evaluate(
        *(runs[0], str(twin), "--baselines", "none", "--episodes", "2"),
        *("--reconstruct-episodes", "0", "--out", str(again)),
    )
    section = read_report(again)["environments"]["ViewPlanning-v1"]
    assert section["aggregates"] == [] and "[2, 2]" in section["aggregate_notes"][0]
    assert "Not aggregated:" in (again / "report.md").read_text()

    # A seed that ran with other env kwargs is left out of the others' aggregate, and said so.
    other = tmp_path / "ppo_seed4"
    shutil.copytree(runs[0], other)
    config = other / run_folder.CONFIG
    text = re.sub(r"(?m)^seed: \d+$", "seed: 4", config.read_text(), count=1)
    config.write_text(
        text.replace(
            "  action_mode: continuous\n", "  action_mode: continuous\n  motion_cost: 0.02\n"
        )
    )
    mixed = tmp_path / "mixed"
    run_evaluate(
        *(*runs, str(other), "--baselines", "none", "--episodes", "2"),
        *("--reconstruct-episodes", "0", "--out", str(mixed)),
    )
    section = read_report(mixed)["environments"]["ViewPlanning-v1"]
    assert [len(a["runs"]) for a in section["aggregates"]] == [2]
    (note,) = section["aggregate_notes"]
    assert "not aggregated with the other ppo runs, it ran with other env kwargs" in note

    # Nor is a seed trained with other hyper-parameters (a sweep is not a set of seeds).
    tuned = tmp_path / "ppo_seed5"
    shutil.copytree(runs[0], tuned)
    config = tuned / run_folder.CONFIG
    text = re.sub(r"(?m)^seed: \d+$", "seed: 5", config.read_text(), count=1)
    config.write_text(re.sub(r"(?m)^(  gamma:) .*$", r"\1 0.97", text, count=1))
    swept = tmp_path / "swept"
    run_evaluate(
        *(*runs, str(tuned), "--baselines", "none", "--episodes", "2"),
        *("--reconstruct-episodes", "0", "--out", str(swept)),
    )
    section = read_report(swept)["environments"]["ViewPlanning-v1"]
    assert [a["runs"] for a in section["aggregates"]] == [[Path(r).name for r in runs]]
    (note,) = section["aggregate_notes"]
    assert "ppo_seed5: not aggregated with the other ppo runs, it ran with other training" in note


def grasp_seed_result(label: str, seed: int, successes: list[bool], training: dict) -> dict:
    """What the report keeps of one trained grasp run's episodes (the fields aggregation reads)."""
    return {
        "label": label,
        "group": "sac",
        "kind": "policy",
        "env_kwargs": {"obs_mode": "state"},
        "training_settings": training,
        "training_seed": seed,
        "episodes": [
            {"instrument": "scalpel", "is_success": success, "seed": 100 + k}
            for k, success in enumerate(successes)
        ],
    }


def test_yes_no_outcomes_get_a_mean_but_no_iqm_across_seeds():
    """The IQM of 0/1 outcomes trims to a distorted rate: three seeds succeeding in 80% of
    episodes each had an 'IQM' of 1.0 beside their mean of 0.8."""
    from agents.report import _environment_section, _training_settings

    training = _training_settings({"env_kwargs": {"obs_mode": "state"}})
    pattern = [True, True, True, True, False] * 4  # 80%
    results = [grasp_seed_result(f"sac_seed{s}", s, pattern, training) for s in (0, 1, 2)]
    (aggregate,) = _environment_section("InstrumentGrasp-v1", results)["aggregates"]
    assert aggregate["mean"] == pytest.approx(0.8)
    assert aggregate["iqm"] is None and aggregate["iqm_ci95"] is None
    assert aggregate["iqm_seed_ci95"] is None
    assert_ci_holds_mean({"mean": aggregate["mean"], "ci95": aggregate["mean_ci95"]})


def test_runs_trained_in_other_env_kwargs_are_not_seeds_of_one_method():
    """evaluate.py scores every run on the held-out split, so a run trained on another split
    (or reward) showed the same evaluation kwargs and was averaged in as one more seed."""
    from agents.report import _environment_section, _training_settings

    procedural = _training_settings({"env_kwargs": {"object_set": "procedural"}})
    library = _training_settings({"env_kwargs": {"object_set": "train"}})
    assert procedural != library
    pattern = [True, False] * 5
    results = [
        grasp_seed_result("sac_seed0", 0, pattern, procedural),
        grasp_seed_result("sac_seed1", 1, pattern, procedural),
        grasp_seed_result("sac_seed2", 2, pattern, library),
    ]
    section = _environment_section("InstrumentGrasp-v1", results)
    assert [a["runs"] for a in section["aggregates"]] == [["sac_seed0", "sac_seed1"]]
    (note,) = section["aggregate_notes"]
    assert note.startswith("sac_seed2: not aggregated") and "(env kwargs," in note


def test_no_probability_of_improvement_over_a_baseline_run_in_other_env_kwargs():
    """The baseline runs in the first policy's env kwargs: a second group's P(improvement)
    over it compared episodes of another view budget and called them paired."""
    from agents.report import _environment_section, _training_settings

    def run(label, seed, budget, kind="policy", group="ppo"):
        return {
            "label": label,
            "group": group,
            "kind": kind,
            "env_kwargs": {"view_budget": budget},
            "training_settings": _training_settings({"env_kwargs": {"view_budget": budget}}),
            "training_seed": seed if kind == "policy" else None,
            "episodes": [
                {"object": "mug", "scale": 1.0, "position": k, "yaw": 0.0, "coverage": c}
                for k, c in enumerate([0.9, 0.8, 0.7])
            ],
        }

    results = [run("a0", 0, 4), run("a1", 1, 4), run("b0", 0, 6), run("b1", 1, 6)]
    results.append(run("four-view", None, 4, kind="baseline", group="four-view"))
    section = _environment_section("ViewPlanning-v1", results)
    four, six = section["aggregates"]
    assert four["runs"] == ["a0", "a1"] and "probability_of_improvement" in four
    assert six["runs"] == ["b0", "b1"] and "probability_of_improvement" not in six
    assert "four-view ran in other env kwargs" in six["no_improvement_because"]


def test_grasp_episodes_pair_only_when_the_instrument_lay_in_the_same_pose():
    """The instrument's name alone would call two episodes of the scissors paired wherever
    each lay on the tray."""
    from agents.report import _environment_section

    def run(label, x):
        episode = {"instrument": "scissors", "start_position": [x, 0.0], "start_yaw": 0.3}
        return {
            "label": label,
            "group": label,
            "kind": "baseline",
            "env_kwargs": {},
            "training_settings": None,
            "training_seed": None,
            "episodes": [{**episode, "is_success": True}],
        }

    assert _environment_section("InstrumentGrasp-v1", [run("a", 0.5), run("b", 0.5)])["paired"]
    assert not _environment_section("InstrumentGrasp-v1", [run("a", 0.5), run("b", 0.51)])["paired"]


# --- bad input --------------------------------------------------------------------------------


def evaluate_fails(*args: str, out: Path | None = None) -> str:
    """stderr of an evaluate.py run that must exit with status 2 (a usage error)."""
    out = out or Path("/nonexistent/never-written")
    result = run_evaluate("--episodes", "1", "--out", str(out), *args, check=False)
    assert result.returncode == 2, result.stderr[-2000:]
    return result.stderr


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--env", "ViewPlaning-v1", "four-view"], "did you mean 'ViewPlanning-v1'"),
        (["--env", "ViewPlanning-v1", "four-veiw"], "did you mean 'four-view'"),
        (["--env", "InstrumentGrasp-v1", "--baselines", "scripted"], "scripted-grasp"),
        (
            ["--env", "InstrumentGrasp-v1", "--baselines", "squeeze,random,squeeze"],
            "--baselines names squeeze more than once",
        ),
        (
            ["--env", "InstrumentGrasp-v1", "squeeze", "squeeze"],
            "'squeeze' is given more than once",
        ),
        (
            ["--env", "ViewPlanning-v1", "four-view", "--baselines", "four-view"],
            "four-view is given both as a contestant and in --baselines; give it once",
        ),
        (
            ["policies/ViewPlanning-v1/ppo", "policies/ViewPlanning-v1/ppo/"],
            "'policies/ViewPlanning-v1/ppo/' is given more than once",
        ),
        (["runs/no/such/run"], "does not exist"),
        # A run folder's name mistyped (no "/") reads as a baseline name: say both.
        (["ppo_sed0"], "'ppo_sed0': no such run folder or model file, and baseline names need"),
        (
            ["--env", "ViewPlanning-v1", "ppo_sed0"],
            "'ppo_sed0' is neither a run folder or model file (none of that name exists) nor",
        ),
        ([], "nothing to evaluate"),
        (
            ["--env", "ViewPlanning-v1", "--env-kwargs", "view_budgt=3"],
            "did you mean 'view_budget'",
        ),
        (["--env", "ViewPlanning-v1", "--episodes", "0"], "--episodes must be at least 1"),
        (["--env", "ViewPlanning-v1", "--video-episodes", "3"], "add --video"),
        (
            ["--env", "InstrumentGrasp-v1", "squeeze", "--save-reconstructions", "2"],
            "--save-reconstructions score ViewPlanning episodes by reconstruction; no",
        ),
        (
            ["--env", "ViewPlanning-v1", "four-view", "--final-model"],
            "--final-model picks a run folder's final model; no source is a run folder",
        ),
        (
            [
                "--env",
                "ViewPlanning-v1",
                "--reconstruct-episodes",
                "0",
                "--save-reconstructions",
                "3",
            ],
            "--reconstruct-episodes, which is 0 here",
        ),
        (["--env", "ViewPlanning-v1", "--seed", "-1"], "--seed must be 0 or more"),
        (
            ["--env", "InstrumentGrasp-v1", "--seed", str(2**64), "--episodes", "1"],
            "--seed must be at most 4294967295 with --episodes 1 (their seeds run to 1844674407",
        ),
        (
            ["--env", "ViewPlanning-v1", "--seed", str(2**32 - 1), "--episodes", "2"],
            "--seed must be at most 4294967294 with --episodes 2 (their seeds run to 4294967296,",
        ),
        (
            ["--env", "ViewPlanning-v1", "four-view", "--env-kwargs", "objects=[no/such.obj]"],
            "mesh file not found: no/such.obj",
        ),
        (
            ["--env", "ViewPlanning-v1", "four-view", "--env-kwargs", "render_mode=human"],
            "render_mode is the report's to set (rgb_array for --video): leave it out of "
            "--env-kwargs",
        ),
        (["policies/ViewPlanning-v1/ppo", "--algo", "sac"], "is a ppo run's, not sac"),
        (
            ["policies/ViewPlanning-v1/ppo", "--raw-observations"],
            "--raw-observations is for a lone model file trained without normalisation",
        ),
        (
            ["policies/ViewPlanning-v1/ppo/policy.zip", "--raw-observations"],
            "no source given is one (a run folder's config.yml",
        ),
        # The real mistake comes first: a mistyped run folder, no source at all.
        (["ppo_sed0", "--raw-observations"], "'ppo_sed0': no such run folder or model file"),
        (["--raw-observations"], "nothing to evaluate"),
        (["--env", "ViewPlanning-v1", "--baselines", "none"], "leaves no contestant"),
        (
            ["--env", "InstrumentGrasp-v1", "squeeze", "--object-set", "train"],
            "--object-set chooses ViewPlanning episodes, but nothing here runs a ViewPlanning task",
        ),
        (
            ["policies/ViewPlanning-v1/ppo", "--env", "InstrumentGrasp-v1"],
            "--env InstrumentGrasp-v1 is not the environment of the runs given (ViewPlanning-v1)",
        ),
    ],
)
def test_bad_input_exits_with_a_message_naming_the_problem(args, message):
    assert message in evaluate_fails(*args)


@pytest.mark.slow
def test_a_model_that_does_not_fit_its_env_fails_before_any_episode(tmp_path):
    out = tmp_path / "report"
    stderr = evaluate_fails(str(SHIPPED_VIEW_POLICY), "--env-kwargs", "view_budget=6", out=out)
    assert "does not fit ViewPlanning-v1" in stderr and "view_history" in stderr
    assert not out.exists()


def test_a_run_folder_given_as_dot_is_labelled_with_its_name(tmp_path, monkeypatch):
    """Labels come from the path as given: "." was labelled "" (its video ``videos/.mp4``)."""
    from agents.contestants import build_contestants

    run_dir = tmp_path / "ppo_seed4"
    shutil.copytree(SHIPPED_VIEW_POLICY, run_dir)
    monkeypatch.chdir(run_dir)
    (policy,) = build_contestants(["."], baselines=[])
    assert policy.label == "ppo_seed4"
    (lone,) = build_contestants([run_folder.POLICY], env_id="ViewPlanning-v1", baselines=[])
    assert lone.label == "ppo_seed4/policy"


def test_a_run_folder_whose_config_names_another_algorithm_fails_cleanly(tmp_path):
    run_dir = tmp_path / "run"
    shutil.copytree(SHIPPED_VIEW_POLICY, run_dir)
    config = run_dir / "config.yml"
    config.write_text(config.read_text().replace("\nalgo: ppo\n", "\nalgo: sac\n"))
    stderr = evaluate_fails(str(run_dir))
    assert "policy.zip' is not a readable SAC model zip" in stderr


def test_a_report_folder_that_is_a_file_fails_cleanly(tmp_path):
    taken = tmp_path / "report"
    taken.write_text("not a folder")
    stderr = evaluate_fails("--env", "ViewPlanning-v1", "four-view", out=taken)
    assert f"cannot write the report into '{taken}'" in stderr
    assert taken.read_text() == "not a folder"


@pytest.mark.parametrize("name", ["report.json", "report.md"])
def test_a_folder_where_the_report_writes_a_file_fails_before_any_episode(tmp_path, name):
    out = tmp_path / "report"
    (out / name).mkdir(parents=True)
    stderr = evaluate_fails("--env", "ViewPlanning-v1", "four-view", out=out)
    assert f"{out / name} is not a file, and a file of that name is written there" in stderr
    assert sorted(p.name for p in out.iterdir()) == [name]


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux's /proc")
def test_a_report_folder_that_cannot_take_files_fails_cleanly():
    # /proc refuses new files even to root, whom permission bits would not stop.
    stderr = evaluate_fails("--env", "ViewPlanning-v1", "four-view", out=Path("/proc/self"))
    assert "cannot write the report into '/proc/self': cannot write into the folder" in stderr


@pytest.mark.parametrize("shipped", ["ViewPlanning-v1/ppo", "InstrumentGrasp-v1/sac"])
def test_a_corrupt_model_zip_fails_cleanly(tmp_path, shipped):
    run = tmp_path / "run"
    shutil.copytree(REPO / "policies" / shipped, run)
    model = run / run_folder.POLICY
    model.write_bytes(model.read_bytes()[:1000])
    stderr = evaluate_fails(str(run))
    # Named as damaged, not as a normalised run's policy without its statistics.
    assert "is not a stable-baselines3 model zip" in stderr and "statistics" not in stderr


def test_a_shipped_folder_has_no_final_model_to_evaluate():
    stderr = evaluate_fails(str(SHIPPED_VIEW_POLICY), "--final-model")
    assert "keeps only its exported policy.zip" in stderr


def test_a_folder_that_is_not_a_run_fails_cleanly(tmp_path):
    assert "is not a run folder" in evaluate_fails(str(tmp_path))


@pytest.mark.slow
def test_missing_normalizer_statistics_fail_cleanly(grasp_run, tmp_path):
    run = tmp_path / "no_stats"
    shutil.copytree(grasp_run, run)
    for name in (run_folder.BEST_NORMALIZER, run_folder.FINAL_NORMALIZER):
        (run / name).unlink()
    assert "statistics" in evaluate_fails(str(run)) and "missing" in evaluate_fails(str(run))


@pytest.mark.slow
def test_a_lone_model_file_needs_its_env_and_its_algorithm_is_read_from_it(grasp_run, tmp_path):
    lone = tmp_path / "policy.zip"
    shutil.copy(grasp_run / run_folder.FINAL_MODEL, lone)
    assert "pass --env" in evaluate_fails(str(lone))
    # The run normalised its observations: without the statistics beside it, the copy would
    # act on raw ones, so it is refused unless told it was trained without them.
    refused = evaluate_fails(str(lone), "--env", "InstrumentGrasp-v1")
    assert "vecnormalize.pkl" in refused and "--raw-observations" in refused
    shutil.copy(grasp_run / run_folder.FINAL_NORMALIZER, tmp_path / run_folder.FINAL_NORMALIZER)
    # With its normaliser beside it the flag would be ignored: refused, not silently dropped.
    with_flag = evaluate_fails(str(lone), "--env", "InstrumentGrasp-v1", "--raw-observations")
    assert "drop --raw-observations" in with_flag
    out = tmp_path / "report"
    in_run = grasp_run / run_folder.FINAL_MODEL
    run_evaluate(
        *(str(lone), str(in_run), "--env", "InstrumentGrasp-v1"),
        *("--baselines", "none", "--episodes", "1", "--out", str(out)),
    )
    contestants = read_report(out)["environments"]["InstrumentGrasp-v1"]["contestants"]
    assert [(c["group"], c["kind"]) for c in contestants] == [("sac", "policy")] * 2
    # Inside its run folder the same file brings the run's config (and normaliser) with it.
    assert contestants[0]["training_seed"] is None and contestants[1]["training_seed"] == 0
    assert (
        contestants[0]["episodes"][0]["instrument"] == contestants[1]["episodes"][0]["instrument"]
    )


def old_style_copy(policy_zip: Path, algo_class, destination: Path) -> Path:
    """``policy_zip``'s model saved as a run's other model files are: nothing in it says
    whether it acts on raw observations."""
    model = algo_class.load(policy_zip, device="cpu")
    delattr(model, run_folder.RAW_OBSERVATIONS)
    model.save(destination)
    return destination


@pytest.mark.parametrize(
    "env_id, algo", [("ViewPlanning-v1", "ppo"), ("InstrumentGrasp-v1", "sac")]
)
def test_a_lone_shipped_policy_zip_names_its_own_algorithm_and_needs_no_flag(
    tmp_path, env_id, algo
):
    from stable_baselines3 import PPO, SAC

    from agents.contestants import ContestantError, policy_contestant

    lone = tmp_path / "policy.zip"
    shutil.copy(REPO / "policies" / env_id / algo / run_folder.POLICY, lone)
    assert policy_contestant(lone, env_id=env_id).group == algo  # it takes raw observations
    other = "sac" if algo == "ppo" else "ppo"
    with pytest.raises(ContestantError, match=f"saved by {algo}, not {other}"):
        policy_contestant(lone, env_id=env_id, algo=other)
    # Any other model zip alone may need statistics it does not have: refused, by name.
    old = old_style_copy(lone, {"ppo": PPO, "sac": SAC}[algo], tmp_path / "model.zip")
    with pytest.raises(ContestantError, match="vecnormalize.pkl beside it.*raw_observations"):
        policy_contestant(old, env_id=env_id)
    assert policy_contestant(old, env_id=env_id, raw_observations=True).group == algo


def test_a_normaliser_of_another_run_beside_a_model_is_refused_before_any_episode(tmp_path):
    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from agents.contestants import ContestantError, policy_contestant

    lone = old_style_copy(SHIPPED_VIEW_POLICY / run_folder.POLICY, PPO, tmp_path / "model.zip")
    grasp_stats = VecNormalize(DummyVecEnv([lambda: gym.make("InstrumentGrasp-v1")]))
    grasp_stats.save(tmp_path / run_folder.FINAL_NORMALIZER)
    with pytest.raises(ContestantError, match="normalises observations of {forces.*different runs"):
        policy_contestant(lone, env_id="ViewPlanning-v1")


def test_a_run_trained_on_its_own_scene_list_is_scored_with_the_baselines_on_the_split(tmp_path):
    from agents.contestants import ContestantError, build_contestants

    run = tmp_path / "ppo_listed"
    shutil.copytree(REPO / "policies" / "ViewPlanning-v1" / "ppo", run)
    config = run / run_folder.CONFIG
    config.write_text(
        config.read_text().replace(
            "  object_set: procedural\n", "  objects: [box, bench]\n  object_set: train\n"
        )
    )
    contestants = build_contestants([str(run)], splits={"ViewPlanning": "held_out"})
    assert [c.label for c in contestants] == ["ppo_listed", "four-view", "greedy-oracle"]
    for contestant in contestants:
        assert "objects" not in contestant.env_kwargs
        assert contestant.env_kwargs["object_set"] == "held_out"
        assert contestant.env_kwargs["action_mode"] == "continuous"  # the run's other kwargs stay
    # A list given for this evaluation is used; the split is chosen by its own flag.
    chosen = build_contestants([str(run)], env_kwargs={"objects": ["arch"]}, baselines=[])
    assert chosen[0].env_kwargs["objects"] == ["arch"] and "object_set" not in chosen[0].env_kwargs
    with pytest.raises(ContestantError, match="object_set, not env_kwargs object_set"):
        build_contestants([str(run)], env_kwargs={"object_set": "train"})
    with pytest.raises(ContestantError, match="object_set and env_kwargs objects=... both"):
        build_contestants(
            [str(run)], env_kwargs={"objects": ["arch"]}, splits={"ViewPlanning": "train"}
        )


def test_the_split_flags_offer_exactly_the_envs_splits():
    import evaluate
    from liuxing_envs.sim.instruments import INSTRUMENT_SETS
    from liuxing_envs.sim.objects import OBJECT_SETS

    assert evaluate.OBJECT_SPLITS == tuple(OBJECT_SETS)
    assert evaluate.INSTRUMENT_SPLITS == tuple(INSTRUMENT_SETS)


@pytest.mark.parametrize(
    "env_id, scene_kwarg, trained_on, other_kwarg",
    [
        ("ViewPlanning-v1", "objects", ["box", "bench"], ("view_budget", 3)),
        ("InstrumentGrasp-v1", "instruments", ["scalpel"], ("force_limit", 4.0)),
    ],
)
def test_a_run_trained_on_a_list_of_items_is_compared_on_the_held_out_split(
    env_id, scene_kwarg, trained_on, other_kwarg
):
    from agents.evaluation import held_out_env_kwargs, make_env
    from liuxing_envs.sim.instruments import INSTRUMENT_SETS
    from liuxing_envs.sim.objects import OBJECT_SETS

    key, value = other_kwarg
    env = make_env(env_id, held_out_env_kwargs(env_id, {scene_kwarg: trained_on, key: value}))
    try:
        if scene_kwarg == "objects":
            assert env.unwrapped.object_names == OBJECT_SETS["held_out"]
        else:
            assert tuple(env.unwrapped.instrument_names) == INSTRUMENT_SETS["held_out"]
        assert getattr(env.unwrapped, key) == value  # the run's other kwargs stay
    finally:
        env.close()


def test_seeds_of_one_configuration_compare_equal_across_config_versions():
    """An older config.yml lacks keys newer runs write with their defaults, and a fine-tune
    names its source by a path of its own: neither makes two seeds two methods."""
    from agents.report import _training_settings

    config = yaml.safe_load((SHIPPED_VIEW_POLICY / run_folder.CONFIG).read_text())
    older = {key: value for key, value in config.items() if key != "eval_env_kwargs"}
    assert config["eval_env_kwargs"] == {}
    assert _training_settings(older) == _training_settings(config)
    tuned = [
        {**config, "init_from": {"run": run, "model": f"{run}/best_model.zip", "sha256": "ab"}}
        for run in ("policies/x", "./policies/x")
    ]
    assert _training_settings(tuned[0]) == _training_settings(tuned[1])
    assert _training_settings(tuned[0]) != _training_settings(config)
    other = {**config, "hyperparams": {**config["hyperparams"], "gamma": 0.9}}
    assert _training_settings(other) != _training_settings(config)


def test_a_misspelt_env_kwarg_in_a_run_config_is_named_with_a_suggestion(tmp_path, capsys):
    """A hand-edited config.yml with ``obs_mod`` used to reach the env's bare TypeError."""
    run = tmp_path / "run"
    shutil.copytree(REPO / "policies" / "InstrumentGrasp-v1" / "sac", run)
    config = (run / "config.yml").read_text()
    (run / "config.yml").write_text(
        config.replace("env_kwargs: {}", "env_kwargs:\n  obs_mod: state")
    )
    import evaluate

    with pytest.raises(SystemExit) as exit_info:
        evaluate.main(
            [str(run), "--baselines", "none", "--episodes", "1", "--out", str(tmp_path / "out")]
        )
    assert exit_info.value.code == 2
    assert "unknown env kwarg 'obs_mod' for InstrumentGrasp-v1 (did you mean 'obs_mode'?)" in (
        capsys.readouterr().err
    )


@pytest.mark.parametrize(
    "env_id, length_kwarg, length",
    [
        ("ViewPlanning-v1", "view_budget", 8),
        ("InstrumentGrasp-v1", "episode_steps", 3),
        ("ViewPlanning-v0", "view_budget", 8),
        ("InstrumentGrasp-v0", "episode_steps", 3),
    ],
)
def test_an_episode_runs_to_the_length_its_kwarg_sets(env_id, length_kwarg, length):
    """Training, periodic evaluation and evaluate.py all make their envs here. The v1 ids end
    their own episodes; a v0 id's registered limit, left at its default, cut the episodes
    short of what the env's reward counts on, so it follows the kwarg."""
    from agents.evaluation import make_env

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        env = make_env(env_id, {length_kwarg: length})
    try:
        env.reset(seed=0)
        env.action_space.seed(0)
        steps, done = 0, False
        while not done and steps < 20:
            _, _, terminated, truncated, _ = env.step(env.action_space.sample())
            steps, done = steps + 1, terminated or truncated
        assert steps == length
        assert env.spec.max_episode_steps == (length if env_id.endswith("-v0") else None)
    finally:
        env.close()


def test_sampled_actions_do_not_depend_on_what_ran_before_in_the_process():
    import torch

    from agents.contestants import policy_contestant
    from agents.evaluation import make_env, run_episodes

    contestant = policy_contestant(REPO / "policies" / "ViewPlanning-v1" / "ppo")
    env = make_env("ViewPlanning-v1", {**contestant.env_kwargs, "object_set": "held_out"})
    policy = contestant.make_policy(env)
    try:
        first = run_episodes(env, policy, [5, 6, 7], ["coverage"], deterministic=False)
        torch.rand(1000)  # another policy sampling in between, as in a report of several
        again = run_episodes(env, policy, [5, 6, 7], ["coverage"], deterministic=False)
    finally:
        env.close()
    assert first == again


def test_a_scan_with_nothing_fused_is_recorded_without_a_chamfer_distance():
    # Its Chamfer distance is infinite, which report.json (strict JSON) cannot hold: the
    # episode records None, and the summary averages the episodes that have one.
    from agents.recorders import ViewPlanningRecorder
    from agents.task_reports import reconstruction_note, view_planning_summary
    from liuxing_envs.envs.view_planning import ViewPlanningEnv

    env = ViewPlanningEnv(objects=["box"], scales=(1.0,), coverage_samples=1024)
    recorder = ViewPlanningRecorder(reconstruct_episodes=2)
    records = []
    for index, empty in enumerate((False, True)):
        _, info = env.reset(seed=index)
        recorder.begin(env, info)
        if empty:
            env.map.reset()  # as if every point had been cropped away
        records.append(recorder.end(env, index, index))
    env.close()
    assert records[0]["chamfer"] > 0 and records[1]["chamfer"] is None
    assert records[1]["fscore"] == 0.0
    summary = view_planning_summary(records)
    assert summary["chamfer"]["n"] == 1 and summary["chamfer"]["mean"] == records[0]["chamfer"]
    json.dumps(records, allow_nan=False)
    # The report's note counts both episodes as reconstructed and says Chamfer averages one.
    note = " ".join(
        reconstruction_note([{"label": "ppo", "summary": summary, "episodes": records}])
    )
    assert "of the first 2 episodes" in note and "averages fewer: ppo 1 of 2" in note


def four_view_report(out: Path, seed: int) -> dict:
    """A one-episode four-view report with one reconstruction saved, written into ``out``."""
    from agents.contestants import build_contestants
    from agents.report import Settings, evaluate

    contestants = build_contestants(["four-view"], env_id="ViewPlanning-v1", baselines=[])
    settings = Settings(episodes=1, seed=seed, reconstruct_episodes=1, save_episodes=1)
    return evaluate(contestants, settings, out)


def test_a_report_into_an_earlier_reports_folder_replaces_its_files_and_no_others(tmp_path):
    out = tmp_path / "report"
    four_view_report(out, seed=5)
    earlier_mesh_folder = out / "reconstructions" / "four-view" / "seed_5"
    assert (earlier_mesh_folder / "ground_truth.ply").is_file()
    stale = earlier_mesh_folder / "reconstruction_mesh_of_another_run.ply"
    stale.write_bytes(b"x")
    (out / "videos").mkdir()
    (out / "videos" / "four-view.mp4").write_bytes(b"x")  # as if the last one had --video
    (out / "videos" / "my_clip.mp4").write_bytes(b"mine")
    (out / "notes.txt").write_text("mine")
    report = four_view_report(out, seed=6)
    assert not earlier_mesh_folder.exists() and not stale.exists()
    assert (out / "reconstructions" / "four-view" / "seed_6" / "ground_truth.ply").is_file()
    assert (out / report["figures"]["coverage_vs_views"]).is_file()
    assert not (out / "videos" / "four-view.mp4").exists()
    assert (out / "videos" / "my_clip.mp4").read_text() == "mine"  # not the report's
    assert (out / "notes.txt").read_text() == "mine"
    assert not (out / ".reconstructions.partial").exists()


def test_a_report_stopped_during_its_episodes_leaves_the_earlier_report_whole(
    tmp_path, monkeypatch
):
    import agents.report

    out = tmp_path / "report"
    four_view_report(out, seed=5)
    before = sorted(p.relative_to(out) for p in out.rglob("*"))

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(agents.report, "run_episodes", stopped)
    with pytest.raises(KeyboardInterrupt):
        four_view_report(out, seed=6)
    after = sorted(p.relative_to(out) for p in out.rglob("*"))
    assert [p for p in after if p.parts[0] != ".reconstructions.partial"] == before


def test_only_an_evaluate_report_json_marks_files_as_an_earlier_reports(tmp_path):
    from agents.report_folder import earlier_report_files
    from agents.task_reports import FIGURE_FILES

    (tmp_path / "report.json").write_text(json.dumps({"figures": {}, "environments": {}}))
    assert earlier_report_files(tmp_path) == []  # another tool's report.json
    (tmp_path / "report.json").write_text("{not json")
    assert earlier_report_files(tmp_path) == []
    earlier = {
        "environments": {"InstrumentGrasp-v1": {"contestants": [{"label": "sac"}]}},
        "seeds": [0, 0],
        "settings": {},
        "figures": {"peak_forces": "peak_forces.png", "videos": ["../outside.mp4"]},
    }
    (tmp_path / "report.json").write_text(json.dumps(earlier))
    named = {
        p.relative_to(tmp_path).as_posix() for p in earlier_report_files(tmp_path, FIGURE_FILES)
    }
    assert {"peak_forces.png", "coverage_vs_views.png", "reconstructions/sac"} <= named
    assert "videos/sac.mp4" in named
    assert not any(".." in name for name in named)  # nothing outside the folder


def test_a_report_folder_holding_files_not_its_own_is_refused_before_any_episode(tmp_path):
    from agents.contestants import ContestantError

    elsewhere = tmp_path / "clips"
    elsewhere.mkdir()
    (elsewhere / "clip.mp4").write_bytes(b"mine")
    out = tmp_path / "report"
    out.mkdir()
    (out / "videos").symlink_to(elsewhere)
    with pytest.raises(ContestantError, match="videos is a link"):
        four_view_report(out, seed=5)
    assert (elsewhere / "clip.mp4").read_text() == "mine"
    # Nor is a reconstructions folder of the contestant's name that no report of ours wrote.
    (out / "videos").unlink()
    own = out / "reconstructions" / "four-view" / "my_scan.ply"
    own.parent.mkdir(parents=True)
    own.write_bytes(b"mine")
    with pytest.raises(ContestantError, match="no earlier report in the folder wrote it"):
        four_view_report(out, seed=5)
    assert own.read_text() == "mine"


def test_a_report_stopped_after_its_numbers_leaves_no_earlier_report_md(tmp_path, monkeypatch):
    """report.md was written last: a report stopped while drawing its figures left the
    earlier report's report.md into the same --out beside its own report.json."""
    import evaluate
    from agents import report

    out = tmp_path / "report"
    argv = ["--env", "InstrumentGrasp-v1", "squeeze", "--baselines", "none", "--episodes", "1"]
    argv += ["--out", str(out), "--no-progress-bar"]
    assert evaluate.main(argv) == 0

    def stopped(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(report, "write_figures", stopped)
    assert evaluate.main([*argv, "--seed", "7"]) == 130
    assert read_report(out)["seeds"] == [7, 7]
    assert "seeds 7-7 " in (out / "report.md").read_text()


def test_a_report_of_a_dirty_checkout_keeps_its_changes_and_a_clean_one_drops_them(
    tmp_path, monkeypatch
):
    """A report names the commit it ran at; with local changes the commit alone does not
    say what ran, so their patch lies beside the report, and a later clean report in the
    same folder must not leave the earlier patch beside it."""
    from agents.contestants import baseline_contestant
    from agents.report import Settings, evaluate

    out = tmp_path / "report"
    contestants = [baseline_contestant("random", "InstrumentGrasp-v1", {"episode_steps": 5})]
    settings = Settings(episodes=1, seed=7, command="evaluate.py random")
    monkeypatch.setattr(run_folder, "git_commit", lambda directory=None: "a" * 40 + "-dirty")
    monkeypatch.setattr(run_folder, "git_diff", lambda directory=None: b"diff --git a/x b/x\n")
    report = evaluate(contestants, settings, out)
    assert (report["git_commit"], report["git_diff"]) == ("a" * 40 + "-dirty", "git_diff.patch")
    assert (out / "git_diff.patch").read_bytes() == b"diff --git a/x b/x\n"
    assert "-dirty with the changes in `git_diff.patch`" in (out / "report.md").read_text()

    monkeypatch.setattr(run_folder, "git_commit", lambda directory=None: "b" * 40)
    report = evaluate(contestants, settings, out)
    assert report["git_commit"] == "b" * 40 and "git_diff" not in report
    assert not (out / "git_diff.patch").exists()
    assert "with the changes" not in (out / "report.md").read_text()


def test_a_v0_run_folder_still_evaluates_and_the_re_keyed_grasp_policy_scores_the_same(
    tmp_path,
):
    """The shipped grasp policy was trained as InstrumentGrasp-v0 with the env kwargs that are
    InstrumentGrasp-v1's defaults: its run folder as it was (v0 id, those kwargs) still
    evaluates, with v0's deprecation warning, and gives the re-keyed folder's episodes."""
    from tests.behaviour_digests import SHIPPED_GRASP_TASK

    old = tmp_path / "old"
    shutil.copytree(REPO / "policies" / "InstrumentGrasp-v1" / "sac", old)
    config = yaml.safe_load((old / "config.yml").read_text())
    config.update(env_id="InstrumentGrasp-v0", env_kwargs=SHIPPED_GRASP_TASK)
    (old / "config.yml").write_text(yaml.safe_dump(config))
    episodes = {}
    for name, run in (("old", old), ("shipped", REPO / "policies" / "InstrumentGrasp-v1" / "sac")):
        out = tmp_path / f"report_{name}"
        result = run_script(
            "evaluate.py", str(run), "--baselines", "none", "--episodes", "2", "--out", str(out),
            env={"PYTHONWARNINGS": "always::DeprecationWarning"},
        )  # fmt: skip
        (section,) = read_report(out)["environments"].values()
        episodes[name] = section["contestants"][0]["episodes"]
        deprecated = "InstrumentGrasp-v0 is deprecated" in result.stderr
        assert deprecated == (name == "old"), result.stderr[-2000:]
    assert episodes["old"] == episodes["shipped"]
