"""The suite's two tiers: the default run, and the cases only ``MFNORMAL_SLOW=1`` adds.

The default run (the README's test command) keeps every contract: each test function runs
with at least one of its cases, chosen where the contract is hardest (the default model, the
richest nested BSDF, both sides of a refracting surface); most statistical checks keep their
full sample counts. ``SLOW`` lists the further cases of a contract the default run already
holds, and the few whole tests whose contract a cheaper test holds too, each with what covers
it in the default run. Tests marked ``@pytest.mark.slow`` in their own module (scale tests,
the walks' other models) are slow as well. ``MFNORMAL_SLOW=1`` runs everything
(docs/testing.md).

Keys are pytest node ids: a key that ends with ``[`` covers the parametrised cases it starts,
and a case id is listed whole.
"""

import os

#: Whether this run is the full suite (``MFNORMAL_SLOW=1``).
FULL = os.environ.get("MFNORMAL_SLOW", "") not in ("", "0")

#: node id (or a prefix ending in "[") -> what holds the contract in the default run
SLOW = {
    # -- Derivatives -----------------------------------------------------------------------------
    "tests/test_inverse.py::test_renders_through_water_carry_the_maps_derivative":
        "AD = FD through a refracting map: test_faithful_transmission's derivative test (η, α, texels)",
    "tests/test_gradients.py::test_walk_derivatives_at_a_flat_and_a_tilted_map[separable-same]":
        "the nonseparable walks' cases",
    "tests/test_gradients.py::test_walk_derivatives_at_a_flat_and_a_tilted_map[separable-specular]":
        "the nonseparable walks' cases",
    "tests/test_render_gradients.py::test_render_forward_gradient_matches_finite_differences[faithful-texel-path]":
        "faithful-texel-prb (the texel's derivative through a render), faithful-strength under path",
    "tests/test_render_gradients.py::test_render_reverse_gradient_matches_finite_differences[faithful-texel-path]":
        "faithful-texel-prb, and reverse = forward under path (test_mi_render_reverse_equals_forward…)",
    "tests/test_render_gradients.py::test_render_forward_gradient_matches_finite_differences[nonseparable-strength-path]":
        "nonseparable-texel-prb",
    "tests/test_render_gradients.py::test_render_reverse_gradient_matches_finite_differences[nonseparable-strength-path]":
        "nonseparable-texel-prb",
    "tests/test_render_gradients.py::test_faithful_nested_alpha_gradient_under_path_and_prb[path]":
        "its prb case; α's derivative under path: test_gradients (every query of the BSDF)",
    "tests/test_prb_walks.py::test_mfnormal_prb_walk_gradients_match_finite_differences_under_environment[separable-specular-strength]":
        "its nonseparable-same case",
    # -- Sampling = evaluation (χ²) and the adjoint ------------------------------------------------
    "tests/test_faithful.py::test_sampler_matches_pdf_chi2[diffuse]":
        "its roughplastic case (a diffuse and a glossy lobe together)",
    "tests/test_faithful.py::test_sampler_matches_pdf_chi2[ggx_0.1]":
        "its roughplastic case; the glossy lobes' consistency: test_sample_eval_pdf_are_consistent[ggx_0.1-*]",
    "tests/test_faithful_transmission.py::test_sampler_matches_pdf_chi2_over_both_hemispheres[glass-80-importance]":
        "its radiance case; the adjoint's sampler: test_sample_eval_pdf_are_consistent_on_both_sides[*-importance]",
    "tests/test_faithful_transmission.py::test_sample_eval_pdf_are_consistent_on_both_sides[glass_0.3-importance]":
        "glass_0.1-importance and principled-importance",
    "tests/test_faithful_transmission.py::test_sample_eval_pdf_are_consistent_on_both_sides[principled-radiance]":
        "glass_0.3-radiance and principled-importance",
    "tests/test_faithful.py::test_sample_eval_pdf_are_consistent[roughplastic-importance]":
        "roughplastic-radiance, and the importance cases of diffuse and ggx",
    "tests/test_analytic.py::test_sampler_matches_pdf_chi2[diffuse]": "its roughplastic case",
    "tests/test_analytic.py::test_sampler_matches_pdf_chi2[ggx_0.1]": "its ggx_0.5 and roughplastic cases",
    "tests/test_faithful_transmission.py::test_path_tracing_equals_light_tracing_through_a_refracting_surface[rough-camera_above-bumps]":
        "rough-camera_above-tilted_bumps and the smooth cases from both sides",
    "tests/test_faithful_transmission.py::test_path_tracing_equals_light_tracing_through_a_refracting_surface[rough-camera_below-bumps]":
        "rough-camera_below-tilted_bumps and the smooth cases from both sides",
    "tests/test_walk.py::test_sampling_matches_evaluation[roughplastic]": "its diffuse and roughconductor cases",
    # -- Energy --------------------------------------------------------------------------------------
    "tests/test_faithful.py::test_energy_never_exceeds_the_nested_albedo[roughplastic_white]":
        "plastic_white, principled and blend (a diffuse and a glossy lobe)",
    "tests/test_faithful_transmission.py::test_rough_dielectric_never_exceeds_the_nested_albedo[glass_0.3]":
        "glass_0.1 and water_0.2",
    "tests/test_faithful_transmission.py::test_rough_dielectric_never_exceeds_the_nested_albedo[principled]":
        "glass_0.1 and water_0.2",
    "tests/test_walk.py::test_white_furnace_albedo_is_one[nonseparable-specular]": "nonseparable-same and separable-specular",
    "tests/test_walk.py::test_white_furnace_albedo_is_one[separable-same]": "separable-specular and nonseparable-same",
    # -- Fuzzing and hostile inputs (the default run keeps one or more cases of each model) ----------
    "tests/test_fuzz.py::test_fuzzed_queries_are_finite_valid_and_bounded[nonseparable-specular-roughplastic]":
        "nonseparable-same and the faithful cases",
    "tests/test_fuzz.py::test_fuzzed_queries_are_finite_valid_and_bounded[nonseparable-specular-plugin_around_twosided]":
        "faithful-specular-plugin_around_twosided, separable-same-plugin_around_twosided",
    "tests/test_fuzz.py::test_fuzzed_queries_are_finite_valid_and_bounded[nonseparable-same-plugin_around_twosided]":
        "faithful-specular-plugin_around_twosided, separable-same-plugin_around_twosided",
    "tests/test_fuzz.py::test_fuzzed_queries_are_finite_valid_and_bounded[separable-same-twosided_around_plugin]":
        "faithful-specular-twosided_around_plugin",
    "tests/test_fuzz.py::test_fuzzed_queries_are_finite_valid_and_bounded[separable-same-roughconductor]":
        "nonseparable-same-roughconductor",
    "tests/test_fuzz.py::test_fuzzed_queries_are_finite_valid_and_bounded[faithful-specular-roughconductor]":
        "faithful-specular-roughplastic (a glossy lobe), nonseparable-same-roughconductor",
    "tests/test_hostile.py::test_hostile_scene_renders_finite_or_fails_in_one_line[normalmap_8192x8192-analytic]":
        "a scale case: the other hostile scenes (the 1×1 map among them) in the default run; an 8192² map at 1080p: test_two_million_triangles_and_8k_normal_map_at_1080p",
    "tests/test_hostile.py::test_render_does_not_depend_on_thread_count[nonseparable]": "its analytic case",
    # -- Renders ------------------------------------------------------------------------------------
    "tests/test_fused.py::test_walks_match_path_in_expectation[separable-specular]": "its nonseparable-same case",
    "tests/test_fused.py::test_walks_match_path_in_expectation[separable-same]": "its nonseparable-same case",
    "tests/test_fused.py::test_walks_match_path_in_expectation[nonseparable-specular]": "its nonseparable-same case",
    "tests/test_normals.py::test_contracts_hold[faithful-geometric_nomap]":
        "faithful-geometric (the geometric macro normal with a map) and the other models' geometric_nomap",
    "tests/test_heightfield.py::test_surface_fills_the_frame[minified-grazing]": "minified-frontal and magnified-grazing",
    "tests/test_prb_walks.py::test_mfnormal_prb_equals_prb_for_deterministic_bsdfs[faithful-texel]":
        "its roughplastic case (mfnormal_prb is prb for a BSDF without walks); the default's render gradients: test_render_gradients",
    # -- The cluster (Dask) -------------------------------------------------------------------------
    "tests/test_cluster.py::test_compare_on_a_local_cluster_shows_the_methods_that_refuse_the_scene":
        "test_compare_on_two_local_workers_of_an_openexr_scene_ends_with_its_report; refusals: test_report",
    "tests/test_cluster.py::test_a_render_whose_scheduler_is_lost_writes_nothing":
        "test_a_render_whose_workers_all_leave_writes_nothing (nothing half-written)",
    "tests/test_cluster.py::test_a_worker_started_with_a_variant_renders_its_chunks_in_it":
        "test_cluster_render_equals_its_chunks_rendered_in_sequence… (the suite's variant)",
    "tests/test_cluster.py::test_a_scheduler_that_never_answers_is_one_line_within_the_timeout[tls]": "its tcp case",
}


def slow_reason(nodeid: str):
    """What holds ``nodeid``'s contract in the default run if it is a slow case, else None."""
    reason = SLOW.get(nodeid)
    if reason is None and "[" in nodeid:
        reason = SLOW.get(nodeid[:nodeid.index("[") + 1])
    return reason
