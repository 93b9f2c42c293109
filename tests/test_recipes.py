"""Recipes: the shipped policies' training, every setting pinned, chained runs by one command."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

import train
from agents import recipes, run_folder
from agents.config import ConfigError
from liuxing_envs.registration import settings_of
from tests.scripts import REPO, run_script

RECIPES = sorted((REPO / "recipes").glob("*.yml"))


def test_each_shipped_policy_has_a_recipe_with_its_seed_and_task():
    from agents import training

    shipped = {}
    for path in RECIPES:
        recipe = recipes.load_recipe(path)  # every stage checked and pinned
        last = recipe.stages[-1]
        shipped[(last["env_id"], last["algo"])] = recipe
    for config_path in (REPO / "policies").glob("*/*/config.yml"):
        config = run_folder.read_config(config_path.parent)
        recipe = shipped[(config["env_id"], config["algo"])]
        assert recipe.seed == config["seed"], recipe.name
        last = recipe.stages[-1]
        trained = settings_of(config["env_id"], **config["env_kwargs"])
        assert settings_of(last["env_id"], **last["env_kwargs"]) == trained
        if len(recipe.stages) == 1:  # trained by one run: the recipe is its configuration
            resolved = training.run_definition(recipes.resolve_stage(last, recipe.seed, None))
            defined = training.run_definition(config)
            # It writes out the algorithm's defaults, which the run's config leaves out.
            assert resolved.pop("hyperparams").items() >= defined.pop("hyperparams").items()
            differ = [k for k in resolved if k != "env_kwargs" and resolved[k] != defined[k]]
            assert differ == [], recipe.name


def _edited(tmp_path: Path, edit) -> Path:
    content = yaml.safe_load((REPO / "recipes" / "view_planning_ppo.yml").read_text())
    edit(content)
    path = tmp_path / "recipe.yml"
    path.write_text(yaml.safe_dump(content))
    return path


def test_a_recipe_that_leaves_a_setting_to_its_default_is_refused_naming_it(tmp_path):
    def unpin(content):
        del content["stages"][0]["env_kwargs"]["motion_cost"]
        del content["stages"][0]["hyperparams"]["vf_coef"]

    with pytest.raises(ConfigError, match="leaves env_kwargs.motion_cost, hyperparams.vf_coef"):
        recipes.load_recipe(_edited(tmp_path, unpin))


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda c: c.update(sed=1), "unknown recipe '.*': key 'sed' \\(did you mean 'seed'\\?\\)"),
        (lambda c: c["stages"][0].update(init_from="ppo"), "init_from 'ppo' is not an earlier"),
        (lambda c: c["stages"][0].pop("n_timesteps"), "stage 1 has no n_timesteps"),
        (lambda c: c["stages"][0]["hyperparams"].update(gamma="high"), "gamma"),
        (lambda c: c["stages"][0]["env_kwargs"].update(view_budget=0), "view_budget"),
    ],
)
def test_a_bad_recipe_is_refused_before_anything_trains(tmp_path, edit, message):
    with pytest.raises(ConfigError, match=message):
        recipes.load_recipe(_edited(tmp_path, edit))


def test_pin_writes_every_setting_of_a_runs_configuration():
    shipped = REPO / "policies" / "ViewPlanning-v1" / "sac"
    config = run_folder.read_config(shipped)
    (stage,) = recipes.pin(shipped, "again")["stages"]
    assert recipes.unpinned(stage) == []
    resolved = recipes.resolve_stage(stage, config["seed"], init_from=None)
    for key in ("env_id", "algo", "n_timesteps", "n_envs", "eval_freq", "final_episodes"):
        assert resolved[key] == config[key], key
    assert resolved["hyperparams"].items() >= config["hyperparams"].items()
    pinned = settings_of(config["env_id"], **resolved["env_kwargs"])
    assert pinned == settings_of(config["env_id"], **config["env_kwargs"])


def test_a_recipe_takes_no_flag_it_pins(capsys):
    with pytest.raises(SystemExit):
        train.main(
            ["--recipe", "recipes/view_planning_ppo.yml", "-n", "300", "--env-kwargs", "a=1"]
        )
    assert "--env-kwargs, --timesteps cannot be given with --recipe" in capsys.readouterr().err


@pytest.mark.slow
def test_a_chained_recipe_runs_with_one_command_and_the_same_command_keeps_what_is_done(
    tmp_path,
):
    content = yaml.safe_load((REPO / "recipes" / "instrument_grasp_sac.yml").read_text())
    for stage in content["stages"]:  # the chain, in miniature
        stage.update(n_timesteps=64, eval_freq=0, save_freq=0, final_episodes=0)
        stage["hyperparams"].update(buffer_size=1_000, learning_starts=0, batch_size=32)
    content["stages"][0]["hyperparams"]["demonstrations"].update(episodes=1, pretrain_steps=5)
    content["stages"][0]["hyperparams"]["start_curriculum"] = None
    recipe_file = tmp_path / "grasp.yml"
    recipe_file.write_text(yaml.safe_dump(content))
    folder = tmp_path / "chain"
    args = ("--recipe", str(recipe_file), "--seed", "5", "--run-dir", str(folder))
    first = run_script("train.py", *args, "--no-progress-bar").stdout
    assert (
        "stage 2 of 2 (fine_tune)" in first and str(folder / "2_fine_tune" / "policy.zip") in first
    )
    scratch, fine = folder / "1_scratch", folder / "2_fine_tune"
    config = run_folder.read_config(fine)
    assert config["seed"] == 5 and config["init_from"]["run"] == str(scratch)
    assert config["init_from"]["replay_buffer"].startswith(str(scratch / run_folder.CHECKPOINTS))
    assert json.loads((scratch / run_folder.DEMONSTRATIONS).read_text())["episodes"] == 1
    policy = (fine / run_folder.POLICY).read_bytes()

    again = run_script("train.py", *args, "--no-progress-bar").stdout
    assert again.count("finished before; kept") == 2
    assert (fine / run_folder.POLICY).read_bytes() == policy
    # A stage stopped after its training (here: before it wrote its policy) is resumed.
    (fine / run_folder.POLICY).unlink()
    resumed = run_script("train.py", *args, "--no-progress-bar").stdout
    assert "(fine_tune): " in resumed and "resumed (writing its policy.zip left)" in resumed
    assert run_folder.takes_raw_observations(fine / run_folder.POLICY)
    # The folder holds seed 5's runs: another seed, or another recipe, is refused.
    other_seed = run_script("train.py", *args[:3], "6", *args[4:], "--no-progress-bar", check=False)
    assert other_seed.returncode == 2
    assert "was trained with another seed than stage 'scratch'" in other_seed.stderr
    recipe_file.write_text(recipe_file.read_text().replace("n_timesteps: 64", "n_timesteps: 65"))
    other_recipe = run_script("train.py", *args, "--no-progress-bar", check=False)
    assert "holds the runs of another recipe" in other_recipe.stderr
