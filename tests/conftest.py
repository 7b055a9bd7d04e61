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
            "test_metadrive_env.py",  # slow: each test over ~1 s (see TEST_CLASS)
            "test_metadrive_rllib.py",
            "test_ppo_critic_inputs.py",
            "test_reproducible.py",
            "test_reproducible_evaluation.py",
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
            "test_gradient_step.py",
            "test_ppo_gae_by_hand.py",
            "test_ppo_precision.py",
            "test_rollout.py",
            "test_td3_family_trace.py",
            "test_traco_learner.py",
        ),
        "integration",
    ),
}
TEST_CLASS: dict[str, str] = {
    # e2e by what they do: train, sweep, start Ray (ray_session), run a coin_app process that trains or evaluates, kill
    **dict.fromkeys(
        (
            "test_arena.py::test_the_committed_pair_loads_without_ray_and_parks_lone_vehicles",
            "test_cig_td3_device.py::test_one_update_and_exploration_on_cuda",
            "test_cig_td3_device.py::test_one_remote_learner_trains_syncs_evaluates_and_checkpoints",
            "test_cli.py::test_train_evaluate_and_resume",
            "test_cluster.py::test_submit_a_smoke_sweep_to_a_local_head_and_follow_it",
            "test_curriculum.py::test_the_training_step_moves_every_env_to_the_full_count_after_the_first_phase",
            "test_copo.py::test_three_advantages_match_a_reference_implementation",
            "test_copo.py::test_copo_trains_moves_the_lcf_and_pushes_it_to_every_env_runner",
            "test_copo.py::test_copo_cli_train_export_evaluate",
            "test_export_formats.py::test_cli_export_each_format",
            "test_export_formats.py::test_cli_export_refuses_bad_input",
            "test_export_formats.py::test_an_export_cut_short_by_the_disk_is_an_oserror_and_leaves_the_earlier_file",
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
            "test_report.py::test_an_evaluation_stopped_and_run_again_with_its_cache_evaluates_only_the_runs_it_had_not",
            "test_report.py::test_missing_or_corrupt_checkpoint_is_reported_by_name_and_the_rest_still_runs",
            "test_report.py::test_report_from_a_real_sweep_writes_every_output",
            "test_report.py::test_report_lists_unreadable_trials_and_still_writes_everything_else",
            "test_report.py::test_validation_selection_scores_the_checkpoint_best_on_validation_seeds",
            "test_report.py::test_report_transfer_pairs_each_model_with_its_own_native_episodes_on_metadrive",
            "test_report.py::test_an_archived_sweep_is_small_evaluates_as_the_sweep_and_cannot_resume_training",
            "test_bad_inputs.py::test_report_killed_with_sigkill_in_its_swap_leaves_the_old_report_whole_and_the_next_report_a_whole_new_one",
            "test_sweeps.py::test_gpu_sweep_on_a_local_ray_without_enough_gpus_is_refused",
            "test_sweeps.py::test_reduced_protocol_runs_end_to_end_at_a_tiny_budget",
            "test_sweeps.py::test_dense_protocol_runs_end_to_end_at_a_tiny_budget",
            "test_sweeps.py::test_ablations_smoke_sweep_end_to_end",
            "test_sweeps.py::test_sweep_logs_every_trial_to_wandb_offline_and_an_mlflow_store",
            "test_sweeps.py::test_sweep_killed_with_sigkill_leaves_no_ray_process_and_resumes_without_rerunning_or_losing_anything",
            "test_sweeps.py::test_sweep_killed_at_random_points_loses_nothing",
            "test_sweeps.py::test_sweep_driver_stopped_with_sigterm_leaves_no_ray_process_and_no_traceback",
        ),
        "e2e",
    ),
    # slow: over ~1 s a test (2-core machine shared with training runs, 2026-11-29), so that -m "not e2e" stays under 2 minutes
    **dict.fromkeys(
        (
            "test_agnn.py::test_evaluate_arena_runs_the_agnn",
            "test_agnn.py::test_suite_runs_the_agnn_in_its_physics_under_both_protocols",
            "test_agnn.py::test_u_attention_matches_the_edge_by_edge_formula",
            "test_architecture.py::test_forbidden_internal_imports_are_absent_directly_and_through_other_modules",
            "test_architecture.py::test_function_level_imports_name_their_reason",
            "test_architecture.py::test_layers_import_only_downward",
            "test_architecture.py::test_no_import_cycles",
            "test_architecture.py::test_nothing_but_main_imports_the_cli",
            "test_architecture.py::test_sim_and_inference_import_without_ray_and_inference_without_torch",
            "test_arena.py::test_avoiding_driver_collides_less_than_the_plain_one_among_obstacles",
            "test_arena.py::test_candidate_features_are_the_capped_clearances_of_rolling_out_every_candidate_against_every_entity",
            "test_arena.py::test_generator_guarantees",
            "test_arena.py::test_heuristic_parks_a_lone_vehicle_every_time",
            "test_arena.py::test_planning_driver_beats_the_avoiding_one_among_vehicles",
            "test_arena.py::test_several_entities_see_more_and_the_suite_observes_what_a_policy_was_trained_on",
            "test_arena.py::test_short_generator_starts_near_the_targets",
            "test_arena.py::test_test_sets_are_fixed_and_disjoint_from_training",
            "test_arena_report.py::test_evaluate_arena_puts_policies_side_by_side_and_report_rebuilds_the_page",
            "test_bad_inputs.py::test_every_algorithm_key_refuses_inf_nan_and_wrong_types_through_train",
            "test_bad_inputs.py::test_a_report_is_replaced_as_one_set_and_an_interrupted_one_leaves_the_old_as_it_was",
            "test_bad_inputs.py::test_sweep_refuses_a_live_writer_of_its_directory_and_takes_a_dead_ones_lock_over",
            "test_bad_inputs.py::test_report_refuses_a_live_writer_of_its_directory_and_takes_a_dead_ones_lock_over",
            "test_bad_inputs.py::test_demo_checks_every_policys_layout_before_any_work",
            "test_bad_inputs.py::test_evaluate_warns_on_a_scene_and_a_count_the_policy_was_not_trained_for",
            "test_batched_runner.py::test_arena_transitions_equal_rllib_runner",
            "test_batched_runner.py::test_driving_batch_of_envs_equals_single_env_runners",
            "test_batched_runner.py::test_driving_transitions_equal_rllib_runner",
            "test_cig_td3_device.py::test_update_and_exploration_create_tensors_on_the_module_device",
            "test_cig_td3_learner.py::test_actor_has_three_hidden_layers_of_hidden_units",
            "test_cig_td3_learner.py::test_actor_step_does_not_touch_critics",
            "test_cig_td3_learner.py::test_actor_waits_actor_start_steps_after_the_warm_up",
            "test_cig_td3_learner.py::test_each_ablation_switch_changes_only_what_it_names",
            "test_cig_td3_learner.py::test_exploration_noise_decays_linearly_after_the_warm_up",
            "test_cig_td3_learner.py::test_learner_state_round_trip_continues_identically",
            "test_cig_td3_learner.py::test_learning_rates_decay_linearly_on_the_env_step_schedule",
            "test_cig_td3_learner.py::test_policy_delay_and_target_updates",
            "test_cig_td3_learner.py::test_same_seed_same_losses_for_50_updates",
            "test_cig_td3_learner.py::test_without_a_decay_the_learning_rates_stay_constant",
            "test_cig_td3_networks.py::test_gradcheck_in_double_precision",
            "test_cig_td3_precision.py::test_bf16_losses_and_gradients_agree_with_fp32",
            "test_cig_td3_replay.py::test_eviction_never_yields_overwritten_data",
            "test_cig_td3_replay.py::test_memory_is_proportional_to_what_is_stored",
            "test_cig_td3_replay.py::test_real_env_runner_stream_matches_the_env_log",
            "test_cig_td3_replay.py::test_rings_growing_from_a_few_rows_store_sample_evict_and_checkpoint_exactly",
            "test_cli.py::test_demo_compares_two_policies_on_one_seed",
            "test_cli.py::test_demo_writes_metrics_gif_and_plot",
            "test_cli.py::test_parsing_and_refusals_import_neither_ray_nor_torch",
            "test_cli.py::test_train_and_config_check_their_settings_before_importing_ray_or_torch",
            "test_compiled_parity.py::test_a_long_seeded_episode_equals_the_numpy_step",
            "test_critic_probe.py::test_probe_weighs_the_global_critic_as_the_actor_does",
            "test_evaluate.py::test_batched_evaluation_equals_sequential_runs",
            "test_evaluate.py::test_evaluation_is_repeatable_and_seed_sets_are_disjoint",
            "test_export_formats.py::test_loading_needs_no_ray",
            "test_heuristic.py::test_batched_outcomes_equal_one_env_at_a_time",
            "test_heuristic.py::test_driver_as_rollout_policy_equals_its_dict_actions",
            "test_heuristic.py::test_single_vehicle_arrives_in_at_least_99_percent_of_200_spawns",
            "test_nav_ppo.py::test_short_generator_scores_the_parking_stages_starts_on_the_held_out_seeds",
            "test_nav_ppo.py::test_suite_is_deterministic_and_its_summary_aggregates_by_hand",
            "test_parking_options.py::test_dagger_rounds_add_the_clones_own_states_labelled_by_the_driver",
            "test_parking_options.py::test_demonstrations_label_every_driving_row_with_the_drivers_own_action",
            "test_parking_options.py::test_intervention_weights_mark_exactly_the_rows_the_filter_changed",
            "test_parking_options.py::test_lone_fraction_mixes_in_single_vehicle_episodes_and_leaves_the_default_stream_unchanged",
            "test_ppo_device.py::test_an_update_creates_tensors_on_the_module_device",
            "test_ppo_precision.py::test_bf16_losses_and_gradients_agree_with_fp32",
            "test_ppo_precision.py::test_the_sgd_steps_run_in_the_configured_precision_and_the_rest_in_fp32",
            "test_ppo_reference.py::test_a_copo_export_reproduces_the_checkpoints_per_vehicle_draws",
            "test_ppo_reference.py::test_the_rollout_names_every_row_by_its_episode_seed_and_agent_id",
            "test_rendering.py::test_trajectory_plot_marks_a_vehicle_that_never_moved",
            "test_rendering.py::test_write_gif_has_every_frame",
            "test_rllib_env.py::test_outcome_counts_match_the_episode_metrics",
            "test_rules.py::test_long_seeded_episodes_give_the_recorded_rewards_terminations_and_infos",
            "test_map_extract.py::test_the_extractor_regenerates_every_committed_map",
            "test_map_extract.py::test_the_native_solid_center_line_is_the_bottleneck_coins_patched_metadrive_builds",
            "test_rollout.py::test_batched_and_dict_paths_equal_a_hand_written_loop",
            "test_rollout.py::test_stops_when_every_episode_is_over",
            "test_shipped.py::test_the_shipped_arena_pair_parks_lone_vehicles_as_recorded",
            "test_shipped.py::test_a_shipped_driving_policy_reaches_its_recorded_test_success",
            "test_shipped.py::test_a_shipped_policy_loads_by_name_with_ray_and_torch_blocked",
            "test_cli.py::test_config_prints_a_reduced_trials_merged_settings_with_their_origins",
            "test_docs_site.py::test_generated_reference_pages_are_those_the_code_gives",
            "test_replay.py::test_page_loads_and_steps_move_vehicles",
            "test_replay.py::test_screenshot_shows_the_marker_where_and_when_it_happened",
            "test_replay.py::test_selected_vehicle_shows_its_outcome",
            "test_replay.py::test_js_errors_are_reported",
            "test_replay.py::test_arena_page_loads",
            "test_simulator.py::test_batched_env_reproduces_single_env",
            "test_simulator.py::test_observations_are_in_unit_box_under_random_driving",
            "test_simulator.py::test_same_seed_same_episode_and_different_seed_differs",
            "test_sweeps.py::test_reduced_scale_is_the_quick_scenario_with_each_familys_protocol_settings",
            "test_td3_chunked_loop.py::test_a_chunk_across_the_warmup_switches_to_the_policy_at_its_step",
            "test_td3_chunked_loop.py::test_a_training_step_samples_k_env_steps_then_their_updates",
            "test_td3_family_trace.py::test_cig_td3_updates_reproduce_the_recorded_trace",
            "test_traco_learner.py::test_actor_step_does_not_touch_critics",
            "test_traco_learner.py::test_each_switch_builds_and_trains",
            "test_traco_learner.py::test_learner_state_round_trip_continues_identically",
            "test_traco_learner.py::test_policy_delay_and_target_updates",
            "test_traco_learner.py::test_same_seed_same_losses_for_50_updates",
            "test_vehicle_replay.py::test_recorder_reproduces_the_shipped_traces",
        ),
        "e2e",
    ),
}


def pytest_sessionstart(session):
    """Compile the simulator's Numba kernels once, before any test: the subprocesses the e2e tests start then load the cache."""
    from coin_app.sim.warm import warm_kernels

    warm_kernels()


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
        speed = TEST_CLASS.get(f"{file}::{name}", FILE_CLASS.get(file, "unit"))
        if "ray_session" in getattr(item, "fixturenames", ()) and speed != "e2e":
            raise pytest.UsageError(f"{item.nodeid} starts Ray (ray_session): its speed class is e2e, not {speed}")
        item.add_marker(speed)
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
