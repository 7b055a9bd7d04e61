"""Shared fixtures, and each test's speed class (``unit``, ``integration``, ``e2e``: ``pytest -m "not e2e"`` is the fast loop)."""

import os

import pytest
import ray
import torch

# ----------------------------------------------------------------------------- speed classes
# e2e: trains, runs a sweep, starts Ray, spawns a coin_app process that trains or evaluates, or kills one (-9, SIGTERM);
# integration: several components together, seconds at most; unit: the rest (the default of a file not named below).
SPEED_CLASSES = ("unit", "integration", "e2e")

# The one table: a test file's class, then the tests (a name covers all its parametrizations) of another class than their file's.
FILE_CLASS: dict[str, str] = {
    **dict.fromkeys(
        (
            "test_algorithm_conformance.py",
            "test_checkpoints.py",
            "test_cig_td3_algorithm.py",
            "test_cig_td3_learning.py",
            "test_metadrive_rllib.py",
            "test_ppo_critic_inputs.py",
            "test_reproducible.py",
            "test_rllib_ppo_smoke.py",
        ),
        "e2e",
    ),
    **dict.fromkeys(
        (
            "test_arena_report.py",
            "test_batched_runner.py",
            "test_cig_td3_learner.py",
            "test_cig_td3_precision.py",
            "test_cig_td3_replay.py",
            "test_evaluate.py",
            "test_metadrive_env.py",
            "test_ppo_precision.py",
            "test_rollout.py",
            "test_traco_learner.py",
        ),
        "integration",
    ),
}
TEST_CLASS: dict[str, str] = {
    **dict.fromkeys(
        (
            "test_arena.py::test_the_committed_pair_loads_without_ray_and_parks_lone_vehicles",
            "test_cig_td3_device.py::test_one_update_and_exploration_on_cuda",
            "test_cig_td3_device.py::test_one_remote_learner_trains_syncs_evaluates_and_checkpoints",
            "test_cli.py::test_train_evaluate_and_resume",
            "test_cluster.py::test_submit_a_smoke_sweep_to_a_local_head_and_follow_it",
            "test_copo.py::test_three_advantages_match_a_reference_implementation",
            "test_copo.py::test_copo_trains_moves_the_lcf_and_pushes_it_to_every_env_runner",
            "test_copo.py::test_copo_cli_train_export_evaluate",
            "test_export_formats.py::test_cli_export_each_format",
            "test_export_formats.py::test_cli_export_refuses_bad_input",
            "test_nav_ppo.py::test_both_stages_train_export_pair_and_evaluate",
            "test_parking_options.py::test_a_curriculum_run_moves_every_env_to_the_scheduled_spread",
            "test_parking_options.py::test_warm_start_clones_the_driver_into_the_learner_and_the_env_runners",
            "test_ppo_device.py::test_one_update_on_cuda",
            "test_ppo_device.py::test_one_remote_learner_trains_and_syncs_the_env_runner",
            "test_ppo_family.py::test_ippo_trains_with_the_paper_hyperparameters",
            "test_ppo_family.py::test_ippo_cli_train_export_evaluate",
            "test_ppo_family.py::test_centralized_variants_train",
            "test_ppo_reference.py::test_paper_scale_sampling_really_gives_4_chunks_of_200_and_an_update_on_1600_env_steps",
            "test_ppo_reference.py::test_a_training_update_adapts_the_kl_coefficient_to_its_last_epoch_mean",
            "test_ppo_reference.py::test_a_per_agent_time_out_bootstraps_with_zero_by_default_and_with_v_as_the_option",
            "test_ppo_reference.py::test_advantages_are_standardized_over_the_real_rows_only",
            "test_report.py::test_generalization_table_from_a_finished_sweep",
            "test_report.py::test_evaluation_is_deterministic_in_process_and_in_workers",
            "test_report.py::test_missing_or_corrupt_checkpoint_is_reported_by_name_and_the_rest_still_runs",
            "test_report.py::test_report_from_a_real_sweep_writes_every_output",
            "test_report.py::test_report_lists_unreadable_trials_and_still_writes_everything_else",
            "test_report.py::test_validation_selection_scores_the_checkpoint_best_on_validation_seeds",
            "test_report.py::test_report_transfer_pairs_each_model_with_its_own_native_episodes_on_metadrive",
            "test_sweeps.py::test_gpu_sweep_on_a_local_ray_without_enough_gpus_is_refused",
            "test_sweeps.py::test_reduced_protocol_runs_end_to_end_at_a_tiny_budget",
            "test_sweeps.py::test_ablations_smoke_sweep_end_to_end",
            "test_sweeps.py::test_sweep_logs_every_trial_to_wandb_offline_and_an_mlflow_store",
            "test_sweeps.py::test_sweep_killed_with_sigkill_leaves_no_ray_process_and_resumes_without_rerunning_or_losing_anything",
            "test_sweeps.py::test_sweep_killed_at_random_points_loses_nothing",
            "test_sweeps.py::test_sweep_driver_stopped_with_sigterm_leaves_no_ray_process_and_no_traceback",
        ),
        "e2e",
    ),
    **dict.fromkeys(
        (
            "test_cig_td3_device.py::test_update_and_exploration_create_tensors_on_the_module_device",
            "test_cli.py::test_demo_compares_two_policies_on_one_seed",
            "test_ppo_device.py::test_an_update_creates_tensors_on_the_module_device",
        ),
        "integration",
    ),
}


@pytest.hookimpl(tryfirst=True)  # before -m selects on the markers
def pytest_collection_modifyitems(config, items):
    """Mark every test with exactly one speed class, from ``FILE_CLASS`` and ``TEST_CLASS``; stale entries are errors."""
    here = os.path.dirname(__file__)
    stale = [f for f in FILE_CLASS if not os.path.exists(os.path.join(here, f))]
    modules = {}
    for item in items:
        file, name = item.path.name, getattr(item, "originalname", item.name)
        if any(item.get_closest_marker(s) for s in SPEED_CLASSES):
            raise pytest.UsageError(f"{item.nodeid}: a speed class is set only in tests/conftest.py's FILE_CLASS / TEST_CLASS")
        item.add_marker(TEST_CLASS.get(f"{file}::{name}", FILE_CLASS.get(file, "unit")))
        modules.setdefault(file, getattr(item, "module", None))
    for key in TEST_CLASS:
        file, name = key.split("::")
        if file in modules and modules[file] is not None and not hasattr(modules[file], name):
            stale.append(key)
    if stale or not set(FILE_CLASS.values()) | set(TEST_CLASS.values()) <= set(SPEED_CLASSES):
        raise pytest.UsageError(f"tests/conftest.py speed table: no such test file or test {stale}, or an unknown class")


# ----------------------------------------------------------------------------- one local Ray for the session
# at least two logical CPUs: a learner and one remote env runner, two sweep trials at once
RAY_ARGS = {"address": "local", "num_cpus": max(2, os.cpu_count() or 1), "include_dashboard": False, "log_to_driver": False}


def _start_ray():
    """Start the session's local Ray unless a Ray is up (a test that stopped it gets it back at its next user)."""
    torch.set_num_threads(1)
    if not ray.is_initialized():
        ray.init(**RAY_ARGS)


@pytest.fixture(scope="session")
def _ray_at_exit():
    """Stops the Ray the tests started, at the end of the session."""
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def ray_session(_ray_at_exit):
    """A local Ray (one for the whole session; one torch thread) for tests and module fixtures that need *a* Ray."""
    _start_ray()


@pytest.fixture(autouse=True)
def _ray_back_up(request):
    """Restarts the session's Ray for a ``ray_session`` test after an earlier test of its module stopped it."""
    if "ray_session" in request.fixturenames:
        _start_ray()


@pytest.fixture
def no_ray():
    """No Ray running when the test starts: a test of code that starts its own Ray (the next ``ray_session`` user restarts it)."""
    if ray.is_initialized():
        ray.shutdown()
