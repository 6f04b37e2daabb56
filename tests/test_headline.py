"""A sweep's headline figures, read from its result files: the parent run's metrics and the
workflow's closing summary."""

import json

from dozerlab import headline
from dozerlab import sweep as P
from dozerlab.config import load_config


def write(path, doc):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc))


def test_metrics_and_summary_from_the_results(tmp_path):
    cfg = load_config(
        {
            "learn": {"models": ["linear", "cnn"]},
            "dynamics": {"models": ["persistence", "ridge", "unet"]},
            "reduced": {"dynamics_models": ["replay", "ridge"]},
        }
    )
    write(P.validation_path(tmp_path, "linear"), {"overall": {"force_x": {"rel_rmse": 0.3}}})
    write(P.validation_path(tmp_path, "cnn"), {"overall": {"force_x": {"rel_rmse": 0.2}}})
    for model, one, far in (("persistence", 0.2, 0.9), ("ridge", 0.1, 0.9), ("unet", 0.05, 1.8)):
        rollout = {"10": {"velocity": 0.5}, "100": {"velocity": far}}
        doc = {"overall": {"one_step": {"velocity": one}, "rollout_at": rollout}}
        write(P.dynamics_validation_path(tmp_path, model), doc)
    points = [
        {"targets_met": {"surface_skill": True, "loop_speedup": False, "job_speedup": None}},
        {"targets_met": {"surface_skill": True, "loop_speedup": True, "job_speedup": None}},
    ]
    overall = {
        "surface_accuracy": 0.72,
        "twin_surface_accuracy": 0.9,
        "surface_accuracy_skill": 0.8,
        "height_accuracy": 0.85,
        "force_x_rel_rmse": 0.2,
        "force_lp_rel_rmse": 0.1,
        "expected_force_lp_rel_rmse_skill": 0.6,  # with twin draws
        "loop_speedup": 40.0,
        "velocity_rel_l2": 0.3,  # not a headline figure
    }
    write(
        P.reduced_comparison_path(tmp_path, "ridge"),
        {"overall": {"all": overall}, "points": points},
    )

    got = headline.metrics(tmp_path, cfg)
    assert got["force_x_rel_rmse/cnn"] == got["force_x_rel_rmse/best"] == 0.2
    assert got["evolution_velocity_error/ridge_rollout_100"] == 0.9
    assert got["reduced_ridge/height_accuracy"] == 0.85
    assert got["reduced_ridge/twin_surface_accuracy"] == 0.9
    assert got["reduced_ridge/surface_accuracy_skill"] == 0.8
    assert got["reduced_ridge/expected_force_lp_rel_rmse_skill"] == 0.6
    assert "reduced_ridge/velocity_rel_l2" not in got
    assert (got["reduced_ridge/targets_met"], got["reduced_ridge/targets_missed"]) == (3.0, 1.0)
    assert not any(k.startswith("reduced_replay") for k in got)  # not built: left out

    lines = headline.summary_lines(tmp_path, cfg, 125.0)
    assert lines[0] == "dozerlab: finished in 2 min 5 s"
    assert "best on held-out points: cnn, force x rel. RMSE 20 % (linear 30 %)" in lines[1]
    assert lines[2].endswith(
        "evolution velocity error over persistence's, held-out points: "
        "ridge 0.50x one step, 1.00x rollout 100; unet 0.25x one step, 2.00x rollout 100"
    )
    assert lines[3].endswith(
        "ridge on 2 held-out points: smoothed-surface accuracy 72 % (twin 90 %, skill 0.80), "
        "low-passed force x rel. RMSE 10 % (0.60 against NDEM's expected run), "
        "height accuracy 85 %, force x rel. RMSE 20 %, least loop speed-up 40.0x"
    )
    assert lines[4].endswith("targets met: surface_skill; missed: loop_speedup (1 of 2)")


def test_with_the_active_zone_the_summary_says_which_ndem_the_speed_ups_are_over(tmp_path):
    overall = {"surface_accuracy": 0.72, "loop_speedup": 16.8, "job_speedup": 10.8}
    points = [{"targets_met": {"loop_speedup": False}}]
    write(
        P.reduced_comparison_path(tmp_path, "ridge"),
        {"overall": {"all": overall}, "points": points},
    )
    reduced = {"dynamics_models": ["ridge"]}
    full = headline.summary_lines(tmp_path, load_config({"reduced": reduced}), 60.0)
    assert full[1].endswith("least loop speed-up 16.8x, least job speed-up 10.8x")
    cfg = load_config({"reduced": reduced, "solver": {"active_zone": {"enabled": True}}})
    zone = headline.summary_lines(tmp_path, cfg, 60.0)
    assert zone[1].endswith(
        "least loop speed-up 16.8x, least job speed-up 10.8x, "
        "speed-ups over NDEM with its active zone"
    )
