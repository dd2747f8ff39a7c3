"""Bad command lines: counts, seeds, names, output paths; and a few odd inputs that must work (exit 0)."""

from __future__ import annotations

from pathlib import Path

from badinputs import Case, Fixtures, write
from badinputs.files import MISSION, SCENARIO, world

RUN = ("run", "{ex}/" + MISSION, "--quiet")
RENDER = ("sim", "render", "{ex}/" + SCENARIO)
TEST = ("test", "{ex}/suite/suite.yaml", "--report", "{case}/reports")
SEED_MAX = str(2**64 - 1)


def a_file(fx: Fixtures, folder: Path) -> None:
    write(folder, "file.txt", "not a folder\n")


def not_a_journal(fx: Fixtures, folder: Path) -> None:
    write(folder, "journal.db", "this is not SQLite\n")


def with_bom(fx: Fixtures, folder: Path) -> None:
    """The example world, its scenario saved by an editor that writes a UTF-8 byte-order mark."""
    world(fx, folder)
    write(folder, SCENARIO, b"\xef\xbb\xbf" + (fx.ex / SCENARIO).read_bytes())


def bench(name: str, *options: str) -> tuple[str, ...]:
    return ("bench", name, *options)


CASES: list[Case] = [
    # seeds
    Case("opt_run_seed_negative", (*RUN, "--seed", "-1"), 2, "--seed: must be an integer in 0..18446744073709551615"),
    Case("opt_run_seed_2_64", (*RUN, "--seed", str(2**64)), 2, "--seed: must be an integer in 0.."),
    Case("opt_run_seed_text", (*RUN, "--seed", "lucky"), 2, "--seed: must be an integer, got 'lucky'"),
    Case("opt_run_seed_float", (*RUN, "--seed", "1.5"), 2, "--seed: must be an integer, got '1.5'"),
    Case(
        "opt_render_seed_negative",
        (*RENDER, "--out", "{case}/f.npz", "--seed", "-5"),
        2,
        "--seed: must be an integer in 0..",
    ),
    Case("opt_render_seed_max_works", (*RENDER, "--out", "{case}/f.npz", "--seed", SEED_MAX), 0, ""),
    Case("opt_bench_missions_seed_negative", bench("missions", "--seed", "-1"), 2, "--seed: must be an integer in 0.."),
    Case("opt_bench_sim_seed_text", bench("sim", "--seed", "x"), 2, "--seed: must be an integer"),
    # counts
    Case("opt_bench_missions_runs_0", bench("missions", "--runs", "0"), 2, "--runs: must be an integer >= 1, got '0'"),
    Case("opt_bench_missions_runs_negative", bench("missions", "--runs", "-3"), 2, "--runs: must be an integer >= 1"),
    Case(
        "opt_bench_missions_jobs_0",
        bench("missions", "--jobs", "0"),
        2,
        "--jobs: must be an integer in 1..256, got '0'",
    ),
    Case(
        "opt_bench_missions_modes_unknown",
        bench("missions", "--modes", "adaptive,fast"),
        2,
        "--modes: unknown 'fast' (known: adaptive,adaptive_truth,no_adapt,paper)",
    ),
    Case("opt_bench_missions_modes_empty", bench("missions", "--modes", ","), 2, "--modes: empty list"),
    Case(
        "opt_bench_missions_families_unknown",
        bench("missions", "--families", "floor,wide"),
        2,
        "--families: unknown 'wide' (known: floor,rack,narrow)",
    ),
    Case("opt_bench_safety_runs_0", bench("safety", "--runs", "0"), 2, "--runs: must be an integer >= 1"),
    Case("opt_bench_safety_jobs_0", bench("safety", "--jobs", "0"), 2, "--jobs: must be an integer in 1..256"),
    Case(
        "opt_bench_safety_families_unknown", bench("safety", "--families", "people"), 2, "--families: unknown 'people'"
    ),
    Case("opt_bench_faults_runs_0", bench("faults", "--runs", "0"), 2, "--runs: must be an integer >= 1"),
    Case(
        "opt_bench_faults_kill_rate_2", bench("faults", "--kill-rate", "2"), 2, "--kill-rate: must be in 0..1, got '2'"
    ),
    Case(
        "opt_bench_faults_kill_rate_nan",
        bench("faults", "--kill-rate", "nan"),
        2,
        "--kill-rate: must be a finite number",
    ),
    Case("opt_bench_sim_frames_0", bench("sim", "--frames", "0"), 2, "--frames: must be an integer >= 1, got '0'"),
    Case(
        "opt_bench_sim_seconds_inf", bench("sim", "--sim-seconds", "inf"), 2, "--sim-seconds: must be a finite number"
    ),
    Case("opt_bench_sim_width", bench("sim", "--width", "1000"), 2, "--width: invalid choice"),
    Case(
        "opt_bench_calibration_poses_0",
        bench("calibration", "--poses", "0"),
        2,
        "--poses: must be an integer >= 1, got '0'",
    ),
    Case(
        "opt_bench_calibration_out_is_file",
        bench("calibration", "--out", "{case}/file.txt"),
        2,
        "file.txt: not a folder",
        a_file,
    ),
    Case("opt_bench_pallet_frames_0", bench("pallet", "--frames", "0"), 2, "--frames: must be an integer >= 1"),
    Case("opt_bench_pallet_labels_unknown", bench("pallet", "--labels", "gt,magic"), 2, "--labels: unknown 'magic'"),
    Case("opt_bench_pallet_ahead_nan", bench("pallet", "--ahead", "nan", "1.0"), 2, "--ahead: must be a finite number"),
    Case("opt_bench_pallet_lateral_negative", bench("pallet", "--lateral", "-1"), 2, "--lateral: must be in 0..1 m"),
    Case("opt_bench_mpc_solver_unknown", bench("mpc", "--solver", "magic"), 2, "--solver: invalid choice: 'magic'"),
    Case("opt_bench_mpc_horizon_0", bench("mpc", "--horizon", "0"), 2, "--horizon: must be an integer in 2..200"),
    Case(
        "opt_bench_mpc_controllers_unknown", bench("mpc", "--controllers", "mpc,pid"), 2, "--controllers: unknown 'pid'"
    ),
    Case("opt_bench_mpc_noise_inf", bench("mpc", "--xy-noise", "inf"), 2, "--xy-noise: must be a finite number"),
    Case("opt_bench_unknown", bench("everything"), 2, "unknown benchmark 'everything'"),
    Case("opt_bench_unknown_option", bench("sim", "--turbo"), 2, "unrecognized arguments: --turbo"),
    Case(
        "opt_segment_dataset_frames_0",
        ("segment", "dataset", "{case}/ds", "--frames", "0"),
        2,
        "--frames: must be an integer >= 1",
    ),
    Case(
        "opt_segment_dataset_seed_negative",
        ("segment", "dataset", "{case}/ds", "--frames", "1", "--seed", "-1"),
        2,
        "--seed: must be an integer in 0..",
    ),
    Case(
        "opt_segment_dataset_start_negative",
        ("segment", "dataset", "{case}/ds", "--frames", "1", "--start", "-1"),
        2,
        "--start: must be an integer >= 0",
    ),
    Case(
        "opt_segment_dataset_out_is_file",
        ("segment", "dataset", "{case}/file.txt", "--frames", "1"),
        2,
        "file.txt: not a folder",
        a_file,
    ),
    Case(
        "opt_segment_eval_frames_0",
        ("segment", "eval", "{case}", "--frames", "0"),
        2,
        "--frames: must be an integer >= 1",
    ),
    Case(
        "opt_capture_count_0", ("capture", "--out", "{case}/cap", "--count", "0"), 2, "--count: must be an integer >= 1"
    ),
    Case(
        "opt_capture_filters_unknown",
        ("capture", "--out", "{case}/cap", "--filters", "spatial,blur"),
        2,
        "--filters: unknown 'blur'",
    ),
    Case("opt_capture_out_is_file", ("capture", "--out", "{case}/file.txt"), 2, "file.txt: not a folder", a_file),
    Case("opt_segment_eval_empty_folder", ("segment", "eval", "{case}"), 2, "no .npz frame bundles"),
    Case(
        "opt_segment_eval_bad_model",
        ("segment", "eval", "{case}", "--model", "{case}/file.txt"),
        2,
        "not a readable ONNX segmentation model",
        a_file,
    ),
    Case(
        "opt_capture_recording_missing",
        ("capture", "--recording", "{case}/nothere.db3", "--out", "{case}/cap"),
        2,
        "no such recording",
    ),
    Case(
        "opt_capture_recording_not_a_bag",
        ("capture", "--recording", "{case}/file.txt", "--out", "{case}/cap"),
        2,
        "not a RealSense recording",
        a_file,
    ),
    Case(
        "opt_capture_live_options_with_recording",
        ("capture", "--recording", "{case}/file.txt", "--out", "{case}/cap", "--fps", "15"),
        2,
        "--fps apply to a live camera",
        a_file,
    ),
    # outputs
    Case(
        "opt_map_show_out_txt",
        ("map", "show", "{ex}/warehouse.yaml", "--out", "{case}/map.txt"),
        2,
        "map.txt: must end in .png",
    ),
    Case(
        "opt_map_show_out_folder",
        ("map", "show", "{ex}/warehouse.yaml", "--out", "{case}"),
        2,
        "is a folder; give a file name",
    ),
    Case(
        "opt_map_show_out_dev_full",
        ("map", "show", "{ex}/warehouse.yaml", "--out", "/dev/full"),
        2,
        "/dev/full: not a regular file",
    ),
    Case(
        "opt_map_show_out_parent_is_file",
        ("map", "show", "{ex}/warehouse.yaml", "--out", "{case}/file.txt/map.png"),
        2,
        "is a file, not a folder",
        a_file,
    ),
    Case("opt_render_out_png", (*RENDER, "--out", "{case}/f.png"), 2, "f.png: must end in .npz"),
    Case("opt_render_out_dev_full", (*RENDER, "--out", "/dev/full"), 2, "/dev/full: not a regular file"),
    Case("opt_render_out_folder", (*RENDER, "--out", "{case}"), 2, "is a folder; give a file name"),
    Case(
        "opt_calibrate_out_txt",
        ("calibrate", "{frame}", "--forks", "{ex}/forks.yaml", "--out", "{case}/c.txt"),
        2,
        "c.txt: must end in .json",
    ),
    Case(
        "opt_calibrate_out_dev_full",
        ("calibrate", "{frame}", "--forks", "{ex}/forks.yaml", "--out", "/dev/full"),
        2,
        "/dev/full: not a regular file",
    ),
    Case(
        "opt_diagram_out_folder",
        ("mission", "diagram", "pickup", "--out", "{case}"),
        2,
        "is a folder; give a file name",
    ),
    Case(
        "opt_diagram_out_dev_full",
        ("mission", "diagram", "pickup", "--out", "/dev/full"),
        2,
        "/dev/full: not a regular file",
    ),
    Case("opt_diagram_unknown_task", ("mission", "diagram", "dance"), 2, "unknown task 'dance'"),
    Case("opt_run_report_is_file", (*RUN, "--report", "{case}/file.txt"), 2, "file.txt: not a folder", a_file),
    Case("opt_run_report_under_file", (*RUN, "--report", "{case}/file.txt/out"), 2, "is a file, not a folder", a_file),
    Case("opt_run_journal_folder", (*RUN, "--journal", "{case}"), 2, "is a folder; give a file name"),
    Case("opt_run_journal_dev_null", (*RUN, "--journal", "/dev/null"), 2, "/dev/null: not a regular file"),
    Case("opt_examples_out_is_file", ("examples", "--out", "{case}/file.txt"), 2, "file.txt: not a folder", a_file),
    # run's own rules
    Case("opt_run_nothing", ("run", "--quiet"), 2, "give a MISSION file"),
    Case("opt_run_demo_and_mission", ("run", "--demo", "{ex}/" + MISSION), 2, "--demo runs the bundled demo"),
    Case(
        "opt_run_resume_and_seed",
        ("run", "--resume", "{case}/j.db", "--seed", "1"),
        2,
        "--resume continues the journal's own run",
    ),
    Case("opt_run_resume_missing", ("run", "--resume", "{case}/nothere.db", "--quiet"), 2, "nothere.db"),
    Case(
        "opt_run_resume_not_sqlite", ("run", "--resume", "{case}/journal.db", "--quiet"), 2, "journal.db", not_a_journal
    ),
    Case("opt_run_clock_unknown", (*RUN, "--clock", "fast"), 2, "--clock: invalid choice: 'fast'"),
    Case("opt_run_unknown_option", (*RUN, "--turbo"), 2, "unrecognized arguments: --turbo"),
    Case("opt_unknown_command", ("fly",), 2, "invalid choice: 'fly'"),
    Case("opt_no_command", (), 2, "the following arguments are required"),
    Case("opt_plan_unknown_nodes", ("plan", "{ex}/warehouse.yaml", "mars", "venus"), 2, "mars"),
    Case("opt_plan_missing_map", ("plan", "{case}/nothere.yaml", "a", "b"), 2, "nothere.yaml: cannot read"),
    # odd but valid
    Case("ok_map_check_example", ("map", "check", "{ex}/warehouse.yaml"), 0, ""),
    Case(
        "ok_render_unicode_folder",
        ("sim", "render", "{case}/lager ü/" + SCENARIO, "--out", "{case}/lager ü/f.npz"),
        0,
        "",
        lambda fx, folder: world(fx, folder / "lager ü"),
    ),
    Case("ok_scenario_with_bom", ("sim", "render", "{case}/" + SCENARIO, "--out", "{case}/f.npz"), 0, "", with_bom),
]

SERVE = ("perception", "serve")
CASES += [
    # perception as a service (`perception serve`, `run --perception`)
    Case("opt_serve_camera_unknown", (*SERVE, "--camera", "kinect"), 2, "--camera: invalid choice: 'kinect'"),
    Case(
        "opt_serve_listen_no_protocol", (*SERVE, "--listen", "127.0.0.1:7447"), 2, "--listen: must be a Zenoh endpoint"
    ),
    Case(
        "opt_serve_connect_port_range",
        (*SERVE, "--connect", "tcp/router:99999"),
        2,
        "--connect: must be tcp/HOST:PORT with a port 0..65535",
    ),
    Case(
        "opt_serve_prefix_wildcard",
        (*SERVE, "--prefix", "palletpilot/*"),
        2,
        "--prefix: must be a key such as palletpilot/perception",
    ),
    Case(
        "opt_serve_model_missing",
        (*SERVE, "--model", "{case}/nothere.onnx"),
        2,
        "nothere.onnx: segmentation model not found",
    ),
    Case("opt_serve_forks_missing", (*SERVE, "--forks", "{case}/nothere.yaml"), 2, "nothere.yaml: cannot read"),
    Case("opt_serve_pallet_unknown", (*SERVE, "--pallet", "crate"), 2, "crate: not a known pallet type"),
    Case("opt_run_perception_unknown", (*RUN, "--perception", "cloud"), 2, "--perception: invalid choice: 'cloud'"),
    Case(
        "opt_run_perception_connect_bad",
        (*RUN, "--perception", "remote", "--perception-connect", "localhost"),
        2,
        "--perception-connect: must be a Zenoh endpoint",
    ),
    Case(
        "opt_run_perception_connect_not_remote",
        (*RUN, "--perception-connect", "tcp/127.0.0.1:7447"),
        2,
        "--perception-connect names the service of --perception remote",
    ),
    Case(
        "opt_run_perception_resume",
        ("run", "--resume", "{case}/j.db", "--perception", "serve-local"),
        2,
        "--resume continues with perception in process",
    ),
    Case(
        "opt_run_perception_remote_nobody",
        (*RUN, "--perception", "remote", "--perception-connect", "tcp/127.0.0.1:1"),
        2,
        "perception service unavailable",
    ),
    Case("opt_test_executor_unknown", (*TEST, "--executor", "dask"), 2, "--executor: invalid choice: 'dask'"),
    Case("opt_test_ray_address_local", (*TEST, "--ray-address", "auto"), 2, "--ray-address: only with --executor ray"),
    Case("opt_test_jobs_0", (*TEST, "--jobs", "0"), 2, "--jobs: must be an integer in 1..256, got '0'"),
]
