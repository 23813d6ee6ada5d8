"""The facegeo command line, run in-process."""

from __future__ import annotations

import subprocess
import sys

import pytest

from facegeo.cli import main


def test_help_is_fast_and_lists_commands():
    out = subprocess.run([sys.executable, "-m", "facegeo.cli", "--help"], capture_output=True,
                         text=True, check=True).stdout
    for cmd in ("synth", "info", "bench", "demo"):
        assert cmd in out
    # --help must not import the heavy dependencies
    code = ("import sys, facegeo.cli; facegeo.cli.build_parser(); "
            "print(sorted(m for m in ('open3d', 'trimesh', 'embreex', 'cv2', 'OpenEXR') if m in sys.modules))")
    heavy = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert heavy.strip() == "[]"


def test_info_reports_a_broken_scan(tmp_path, capsys):
    root = tmp_path / "demo"
    assert main(["synth", str(root), "--preset", "tiny", "-q"]) == 0
    capsys.readouterr()
    victim = sorted((root / "olat" / "cam_right").glob("*.exr"))[5]
    victim.unlink()
    assert main(["info", str(root)]) == 2
    err = capsys.readouterr().err
    assert "cam_right" in err and victim.name in err


def test_synth_rejects_bad_arguments(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["synth", str(tmp_path / "x"), "--preset", "huge"])
    assert main(["synth", str(tmp_path / "x"), "--preset", "tiny", "--head", str(tmp_path / "nope.obj"), "-q"]) == 2
    assert "no such mesh file" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()  # nothing written for bad arguments


# =========================================================================== bad inputs
#
# Every bad input: exit status 2 (or the documented code), exactly one non-empty line on stderr
# naming the value or file, and no traceback.

import json
import os
import shutil

import numpy as np

from facegeo.capture.imageio import read_image, write_image
from facegeo.checks import fmt_value


@pytest.fixture(scope="module")
def tiny_scan_master(tmp_path_factory):
    """One tiny synthetic scan per module; tests copy it (``tiny_scan``) before breaking it."""
    root = tmp_path_factory.mktemp("cli") / "tiny"
    assert main(["synth", str(root), "--preset", "tiny", "-q"]) == 0
    return root


@pytest.fixture
def tiny_scan(tiny_scan_master, tmp_path):
    root = tmp_path / "scan"
    shutil.copytree(tiny_scan_master, root)
    return root


def _unwritable_dir(tmp_path):
    """A directory in which no file can be created, also for root (which ignores mode bits)."""
    if os.geteuid() == 0:
        return "/proc"  # procfs refuses new files even to root
    d = tmp_path / "readonly"
    d.mkdir()
    d.chmod(0o500)
    return str(d)


def _stderr_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.strip()]


def _bad_inputs(tmp_path, scan):
    """``[(argv, expected status, words the single stderr line must contain)]``."""
    a_file = tmp_path / "a_file.txt"
    a_file.write_text("not a directory")
    ro = _unwritable_dir(tmp_path)
    rig = json.loads((scan / "rig.json").read_text())
    rig["cameras"][0]["K"][0][0] = "366"
    (scan / "rig.json").write_text(json.dumps(rig))
    return {
        "seed -1": (["synth", str(tmp_path / "new"), "--seed", "-1", "-q"], 2,
                    ["--seed", "-1", "integer >= 0"]),
        "seed text": (["synth", str(tmp_path / "new"), "--seed", "x", "-q"], 2, ["--seed", "'x'"]),
        "noise -0.1": (["synth", str(tmp_path / "new"), "--noise", "-0.1", "-q"], 2,
                       ["--noise", "-0.1"]),
        "OUT is a file": (["synth", str(a_file), "--preset", "tiny", "-q"], 2,
                          ["OUT", str(a_file), "existing file"]),
        "OUT under a file": (["synth", str(a_file / "sub"), "--preset", "tiny", "-q"], 2,
                             ["OUT", str(a_file), "not a directory"]),
        "OUT not writable": (["synth", f"{ro}/facegeo-scan", "--preset", "tiny", "-q"], 2,
                             ["OUT", ro, "writable"]),
        "bench --out is a file": (["bench", "--quick", "--out", str(a_file)], 2,
                                  ["--out", str(a_file), "existing file"]),
        "bench --out not writable": (["bench", "--quick", "--out", f"{ro}/bench"], 2,
                                     ["--out", ro, "writable"]),
        "rig string focal length": (["info", str(scan)], 2,
                                    ["rig.json", "cameras[0].K[0][0]", "'366'", "JSON number"]),
        "demo SCAN is a file": (["demo", str(a_file), "--preset", "tiny", "-q"], 2,
                                ["SCAN", str(a_file)]),
        "unknown preset": (["synth", str(tmp_path / "new"), "--preset", "huge"], 2,
                           ["--preset", "'huge'"]),
        "no such scan": (["info", str(tmp_path / "nowhere")], 2,
                         [str(tmp_path / "nowhere"), "not found"]),
        "project --gt-lights 0": (["project", str(scan), "--gt-lights", "0"], 2,
                                  ["--gt-lights", "integer >= 1"]),
        # an option's message states the bound the option has (was ">= 0" for ">= 1" options)
        "render --supersample -2": (["render", str(scan), "--camera", "front",
                                     "--supersample", "-2"], 2,
                                    ["--supersample", "integer >= 1", "-2"]),
        "render --supersample text": (["render", str(scan), "--camera", "front",
                                       "--supersample", "abc"], 2,
                                      ["--supersample", "integer >= 1", "'abc'"]),
        "render --light-step -1": (["render", str(scan), "--camera", "front",
                                    "--light-step", "-1"], 2,
                                   ["--light-step", "integer >= 1", "-1"]),
        "atlas --texels-per-mm nan": (["atlas", str(scan), "--texels-per-mm", "nan"], 2,
                                      ["--texels-per-mm", "finite number > 0", "nan"]),
        "info on a file": (["info", str(a_file)], 2, [str(a_file), "not a directory"]),
        "relight unknown env": (["relight", str(scan), "--env", "skyy"], 2,
                                ["skyy", "not a file", "sky, studio"]),
        "relight --rotate inf": (["relight", str(scan), "--env", "sky", "--rotate", "inf"], 2,
                                 ["--rotate", "inf", "360"]),
    }


BAD_INPUTS = ["seed -1", "seed text", "noise -0.1", "OUT is a file", "OUT under a file",
              "OUT not writable", "bench --out is a file", "bench --out not writable",
              "rig string focal length", "demo SCAN is a file", "unknown preset", "no such scan",
              "project --gt-lights 0", "render --supersample -2", "render --supersample text",
              "render --light-step -1", "atlas --texels-per-mm nan", "info on a file",
              "relight unknown env", "relight --rotate inf"]


@pytest.mark.parametrize("case", BAD_INPUTS)
def test_bad_input_gives_one_line_and_status_2(case, tmp_path, tiny_scan, capfd, monkeypatch):
    import facegeo.bench as bench
    import facegeo.synth.capture as synth_capture

    def must_not_run(*a, **k):
        raise AssertionError("the work started before the arguments were checked")

    # bad output paths must be caught before any benchmark runs or any scan is generated
    monkeypatch.setattr(bench, "run_benchmarks", must_not_run)
    monkeypatch.setattr(synth_capture, "generate_scan", must_not_run)
    argv, status, words = _bad_inputs(tmp_path, tiny_scan)[case]
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse
        code = exc.code
    err = capfd.readouterr().err
    lines = _stderr_lines(err)
    assert code == status, err
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert lines[0].startswith("facegeo")
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert not (tmp_path / "new").exists()


# ============================================ arguments checked before the stages they follow
#
# `facegeo render` runs atlas, project and fit first and `facegeo calibrate` detects every
# board: a typo in their own arguments must fail before that work, not minutes after it.


def _early_inputs(tmp_path):
    """``{case: (argv after the command's SCAN, words the single stderr line must contain)}``."""
    a_file = tmp_path / "a_file.txt"
    a_file.write_text("not an image")
    render = ["render", "SCAN", "--camera"]
    return {
        "unknown camera": (render + ["orbit:fronnt:30"],
                           ["camera spec", "'fronnt'", "cam_left, cam_right"]),
        "missing camera file": (render + [str(tmp_path / "cam.json")],
                                [str(tmp_path / "cam.json"), "does not exist"]),
        "absurd orbit angle": (render + ["orbit:front:1e308"], ["1e308", "<= 360"]),
        "unknown env": (render + ["front", "--env", "skyy"],
                        ["env", "skyy", "uniform, axis_lobes, sky, studio"]),
        "missing env file": (render + ["front", "--env", str(tmp_path / "nope.exr")],
                             [str(tmp_path / "nope.exr"), "not a file"]),
        "env file not an image": (render + ["front", "--env", str(a_file)],
                                  [str(a_file), "unsupported image format"]),
        "shrinkage 2": (render + ["front", "--shrinkage", "2"], ["shrinkage", "[0, 1]", "2"]),
        "shrinkage text": (render + ["front", "--shrinkage", "most"], ["shrinkage", "'most'"]),
        "light step 1000": (render + ["front", "--light-step", "1000"],
                            ["light_step", "1000", "(16, 8)"]),
        "rotate nan": (render + ["front", "--rotate", "nan"], ["--rotate", "nan", "360"]),
        "calibrate reference": (["calibrate", "SCAN", "--reference", "cam_mid"],
                                ["reference", "'cam_mid'", "cam_left, cam_right"]),
    }


EARLY_INPUTS = ["unknown camera", "missing camera file", "absurd orbit angle", "unknown env",
                "missing env file", "env file not an image", "shrinkage 2", "shrinkage text",
                "light step 1000", "rotate nan", "calibrate reference"]


@pytest.mark.parametrize("case", EARLY_INPUTS)
def test_render_and_calibrate_check_their_arguments_before_any_stage(case, tmp_path,
                                                                      tiny_scan_master, capfd,
                                                                      monkeypatch):
    import facegeo.geometry.calibration as calibration
    import facegeo.pipeline.reconstruct as reconstruct
    import facegeo.pipeline.render as render

    def must_not_run(*a, **k):
        raise AssertionError("a stage started before the arguments were checked")

    # the calibrate stage's own work starts with the board detection (its argument checks
    # come first in calibrate_products)
    for mod, name in ((reconstruct, "run_reconstruct"), (render, "run_render"),
                      (calibration, "detect_boards")):
        monkeypatch.setattr(mod, name, must_not_run)
    scan = tmp_path / "scan"
    shutil.copytree(tiny_scan_master, scan)
    argv, words = _early_inputs(tmp_path)[case]
    try:
        code = main([str(scan) if a == "SCAN" else a for a in argv])
    except SystemExit as exc:  # argparse
        code = exc.code
    err = capfd.readouterr().err
    lines = _stderr_lines(err)
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert not (scan / "out").exists()  # no stage product (out/atlas, out/calibrate, ...)


def test_atlas_size_0_names_the_size_range(tiny_scan, capfd):
    # was "texels_per_mm and size: give one resolution, not both" (0 read as "no --size")
    assert main(["atlas", str(tiny_scan), "--size", "0"]) == 2
    lines = _stderr_lines(capfd.readouterr().err)
    assert len(lines) == 1 and "size: expected an integer in [16, 32768], got 0" in lines[0]


def _run(args, **kw):
    return subprocess.run([sys.executable, "-m", "facegeo.cli", *args], capture_output=True,
                          text=True, timeout=120, **kw)


def test_not_an_exr_and_truncated_exr_in_a_scan_one_line_without_library_noise(tiny_scan):
    # A subprocess, so that what the OpenEXR C library writes to fds 1 and 2 is captured too.
    frames = sorted((tiny_scan / "olat" / "cam_left").glob("*.exr"))
    fake = frames[40]
    fake.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(300))
    r = _run(["info", str(tiny_scan)])
    lines = _stderr_lines(r.stderr)
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert fake.name in lines[0] and "not an OpenEXR file" in lines[0]
    assert "parts" not in r.stderr and "EXR_ERR" not in r.stderr + r.stdout
    # a middle frame whose compressed data is overwritten (header and chunk table intact):
    # OpenEXR itself fails while decoding and prints its own warnings
    write_image(fake, read_image(frames[41]))
    data = bytearray(frames[60].read_bytes())
    n = len(data) // 2
    data[n:n + 400] = np.random.default_rng(0).integers(0, 255, 400, dtype=np.uint8).tobytes()
    frames[60].write_bytes(bytes(data))
    r = _run(["info", str(tiny_scan), "--full"])
    lines = _stderr_lines(r.stderr)
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert frames[60].name in lines[0] and "corrupt OpenEXR file" in lines[0]
    assert "Warning" not in r.stdout + r.stderr and "EXR_ERR" not in r.stdout + r.stderr


@pytest.mark.parametrize("args, status", [
    (["--help"], 0),  # argparse itself ignores a failed help write
    (["synth", "--help"], 0),
    (["info", "SCAN"], 141),  # was a BrokenPipeError traceback and status 1
    (["info", "SCAN", "--full"], 141),
])
def test_output_into_a_closed_pipe_exits_quietly(args, status, tiny_scan):
    # `facegeo ... | head -1`: the reader goes away before facegeo writes. Close our end of the
    # pipe at once; facegeo's write then fails with EPIPE (BrokenPipeError in Python).
    args = [str(tiny_scan) if a == "SCAN" else a for a in args]
    with subprocess.Popen([sys.executable, "-m", "facegeo.cli", *args], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE) as p:  # closes stderr too (no ResourceWarning)
        p.stdout.close()
        err = p.stderr.read().decode()
        code = p.wait(timeout=120)
    assert err.strip() == "", err  # no traceback, no "Exception ignored ... BrokenPipeError"
    assert code == status


def test_internal_error_is_one_line_and_traceback_only_with_v(tiny_scan, capfd, monkeypatch):
    import facegeo.capture.scan as scanmod

    def broken(scan):
        return 1 / 0

    monkeypatch.setattr(scanmod, "summarize", broken)
    assert main(["info", str(tiny_scan)]) == 1
    err = capfd.readouterr().err
    lines = _stderr_lines(err)
    assert len(lines) == 1 and "Traceback" not in err
    assert lines[0] == ("facegeo info: internal error: ZeroDivisionError: division by zero; "
                        "rerun with -v for the traceback")
    # -v works after the subcommand too, and shows the traceback
    for argv in (["info", str(tiny_scan), "-v"], ["-v", "info", str(tiny_scan)],
                 ["info", "--debug", str(tiny_scan)]):
        assert main(argv) == 1
        err = capfd.readouterr().err
        assert "Traceback" in err and "ZeroDivisionError" in err, argv


def test_user_errors_show_a_traceback_only_with_debug(tiny_scan, capfd):
    (tiny_scan / "rig.json").write_text("{")
    assert main(["info", str(tiny_scan), "-v"]) == 2
    assert "Traceback" not in capfd.readouterr().err
    assert main(["info", str(tiny_scan), "--debug"]) == 2
    err = capfd.readouterr().err
    assert "Traceback" in err and err.rstrip().splitlines()[-1].startswith("facegeo info: error:")


def test_keyboard_interrupt_is_130(tiny_scan, capfd, monkeypatch):
    import facegeo.capture.scan as scanmod

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(scanmod, "load_scan", interrupted)
    assert main(["info", str(tiny_scan)]) == 130
    assert _stderr_lines(capfd.readouterr().err) == ["interrupted"]


def test_verbose_counts_before_and_after_the_command_add_up():
    from facegeo.cli import build_parser

    args = build_parser().parse_args(["-v", "info", "x", "-v"])
    assert args.verbose + args.sub_verbose == 2
    args = build_parser().parse_args(["info", "x", "-vv"])
    assert args.verbose + args.sub_verbose == 2
    args = build_parser().parse_args(["-v", "info", "x"])
    assert args.verbose + args.sub_verbose == 1  # the subparser's default does not reset it


@pytest.mark.parametrize("cmd, shown", [
    ("synth", ["(default: small)", "(default: procedural)", "(default: cm)", "(default: 0)",
               "(default: regional)", "(default: exr)", "(default: 0.0)"]),
    ("bench", ["(default: bench-out)"]),
    ("demo", ["(default: scans/demo)", "(default: small)"]),
])
def test_help_shows_defaults(cmd, shown):
    out = _run([cmd, "--help"]).stdout
    flat = " ".join(out.split())
    for s in shown:
        assert s in flat, (s, out)


def test_messages_print_plain_numbers():
    assert fmt_value(np.float64(0.5)) == "0.5"
    assert fmt_value(np.float32(0.1)) == "0.1"
    assert fmt_value(np.int64(7)) == "7"
    assert fmt_value(np.array([0.5, np.nan])) == "[0.5, nan]"
    assert fmt_value("366") == "'366'"
    from facegeo.checks import check_positive
    from facegeo.errors import InputError

    with pytest.raises(InputError) as info:
        check_positive(np.float64(-0.5), "sigma")
    assert str(info.value) == "sigma: expected a finite number > 0, got -0.5"


# =========================================================================== info on frames


def _info(scan, *extra):
    return main(["info", str(scan), *extra])


def test_info_checks_every_header_and_says_how_many(tiny_scan, capsys):
    assert _info(tiny_scan) == 0
    out = capsys.readouterr().out
    n = sum(1 for p in tiny_scan.rglob("*") if p.suffix in (".png", ".exr")
            and "ground_truth" not in p.parts)
    assert f"checked headers of {n} frames" in out


def test_info_quick_catches_a_truncated_middle_frame_by_name(tiny_scan, capfd):
    victim = sorted((tiny_scan / "olat" / "cam_right").glob("*.exr"))[64]
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) - 100])  # header intact, last chunk cut
    assert _info(tiny_scan) == 2
    lines = _stderr_lines(capfd.readouterr().err)
    assert len(lines) == 1 and victim.name in lines[0] and "cam_right" in lines[0]
    assert "truncated" in lines[0]
    # a truncated PNG in the middle of the structured-light group too
    write_image(victim, read_image(sorted(victim.parent.glob("*.exr"))[63]))
    png = sorted((tiny_scan / "structured_light" / "cam_left").glob("*.png"))[18]
    data = png.read_bytes()
    png.write_bytes(data[: len(data) // 2])
    assert _info(tiny_scan) == 2
    lines = _stderr_lines(capfd.readouterr().err)
    assert len(lines) == 1 and png.name in lines[0] and "truncated" in lines[0]


def test_info_full_catches_a_nan_frame_by_name(tiny_scan, capfd):
    victim = sorted((tiny_scan / "olat" / "cam_left").glob("*.exr"))[70]
    img = read_image(victim)
    img[10, 20, 1] = np.nan
    write_image(victim, img)
    assert _info(tiny_scan) == 0  # the header is fine: quick passes
    capfd.readouterr()
    assert _info(tiny_scan, "--full") == 2
    lines = _stderr_lines(capfd.readouterr().err)
    assert len(lines) == 1 and victim.name in lines[0] and "cam_left" in lines[0]
    assert "1 pixel(s) are NaN" in lines[0] and "(10, 20)" in lines[0]
    img[10, 20, 1] = np.inf
    write_image(victim, img)
    assert _info(tiny_scan, "--full") == 2
    assert "infinite" in capfd.readouterr().err


def test_info_full_warns_about_negative_and_black_frames_by_name(tiny_scan, capfd):
    frames = sorted((tiny_scan / "olat" / "cam_left").glob("*.exr"))
    neg, black = frames[20], frames[30]
    img = read_image(neg)
    img[5, 5] = -0.25
    write_image(neg, img)
    write_image(black, np.zeros_like(read_image(black)))
    assert _info(tiny_scan) == 0
    assert "warning" not in capfd.readouterr().out  # warnings need the pixels: --full only
    assert _info(tiny_scan, "--full") == 0
    out = capfd.readouterr().out
    assert f"warning: olat/cam_left/{neg.name}: negative radiance in 1 pixel(s) (min -0.25)" in out
    assert f"warning: olat/cam_left/{black.name}: all black" in out


def test_info_full_warns_about_a_saturated_frame(tiny_scan, capfd):
    png = sorted((tiny_scan / "structured_light" / "cam_right").glob("*.png"))[10]
    img = read_image(png)
    write_image(png, np.full_like(img, np.iinfo(img.dtype).max))
    assert _info(tiny_scan, "--full") == 0
    out = capfd.readouterr().out
    assert f"warning: structured_light/cam_right/{png.name}: saturated: 100 %" in out


def test_info_counts_hard_linked_files_once(tiny_scan, capsys):
    assert _info(tiny_scan) == 0
    before = [ln for ln in capsys.readouterr().out.splitlines() if "size on disk" in ln]
    big = max((p for p in tiny_scan.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)
    os.link(big, tiny_scan / "a_hard_link_of_the_biggest_file")
    (tiny_scan / "out").mkdir(exist_ok=True)
    os.link(big, tiny_scan / "out" / "another_link")
    assert _info(tiny_scan) == 0
    after = [ln for ln in capsys.readouterr().out.splitlines() if "size on disk" in ln]
    assert after[0].split("(inputs)")[0] == before[0].split("(inputs)")[0]
    assert after[0].endswith("0 B (out/)")


def test_calibrate_table_on_a_real_data_set(shared_data, tmp_path, capsys):
    """``facegeo calibrate`` on OpenCV's stereo chessboards: readable column headers, the
    errors against the data set's reference calibration in the table (they printed '-': the
    table read only the synthetic ground truth's keys), and the view the detector skipped
    named with its reason (it was only in detections.json)."""
    src = shared_data / "calibration" / "opencv_stereo_chessboards"
    if not src.is_dir():
        pytest.skip(f"{src} is absent")
    scan = tmp_path / "st"
    assert main(["import", str(src), str(scan), "--dataset", "opencv-stereo"]) == 0
    capsys.readouterr()
    # a view without a board (the import hard-links the frames: unlink, never write through)
    import cv2

    blank = scan / "calib" / "right" / "view_002.jpg"
    size = cv2.imread(str(blank), 0).shape
    ino = blank.stat().st_ino
    original = next((f, f.read_bytes()) for f in src.iterdir() if f.stat().st_ino == ino) \
        if any(f.stat().st_ino == ino for f in src.iterdir()) else None
    blank.unlink()
    cv2.imwrite(str(blank), np.full(size, 128, np.uint8))
    if original is not None:  # linked: the data set's file is untouched
        assert original[0].read_bytes() == original[1]
    assert main(["calibrate", str(scan), "-q"]) == 0
    out = capsys.readouterr().out.splitlines()
    head = next(line for line in out if line.startswith("camera"))
    assert "focal err" in head and "reference calibration" in head, head
    for cam in ("left", "right"):
        row = next(line for line in out if line.startswith(cam)).split()
        assert "-" not in row[-2:], row  # focal and principal-point errors are numbers
        assert float(row[-2]) < 0.01, row  # measured 0.0041 / 0.0011 (docs/calibration.md)
    assert any(line.startswith("skipped right view 2 (calib/right/view_002.jpg): no 9×6 "
                               "chessboard found") for line in out), out


def test_project_prints_a_line_per_camera(tiny_scan, capsys):
    """``facegeo project`` prints each camera's figures (its ``cameras:`` line was empty: the
    per-camera entries are dicts, which the flat printer left out)."""
    assert main(["project", str(tiny_scan), "--gt-lights", "4", "--camera", "cam_left"]) == 0
    out = capsys.readouterr().out.splitlines()
    i = out.index("  cameras:")
    assert out[i + 1].startswith("    cam_left: ") and "visible_fraction=" in out[i + 1], out


def test_no_shadow_taps_reaches_the_project_stage(monkeypatch, tiny_scan):
    """``--no-shadow-taps`` is the project stage's ``shadow_taps=False``: through the cached
    stage (a setting, so its key changes) and on its own (``--camera``)."""
    import facegeo.pipeline.project as project
    import facegeo.pipeline.reconstruct as reconstruct

    seen = []
    monkeypatch.setattr(reconstruct, "run_reconstruct",
                        lambda *a, **k: seen.append(k.get("settings")) or [])
    monkeypatch.setattr("facegeo.cli._stage_metrics", lambda results, name: {})
    monkeypatch.setattr("facegeo.cli._write_report", lambda out: None)
    monkeypatch.setattr(project, "run_project",
                        lambda *a, **k: seen.append(k.get("shadow_taps")) or {})
    assert main(["project", str(tiny_scan), "--no-shadow-taps", "-q"]) == 0
    assert main(["project", str(tiny_scan), "-q"]) == 0
    assert main(["project", str(tiny_scan), "--camera", "cam_left", "--no-shadow-taps"]) == 0
    assert seen[0]["project"]["shadow_taps"] is False, seen
    assert "shadow_taps" not in seen[1]["project"], seen  # the default: the stage's own True
    assert seen[2] is False, seen


def test_no_shadow_taps_and_no_image_detail_reach_the_render(monkeypatch, tiny_scan):
    """``facegeo render --no-shadow-taps`` / ``--no-image-detail`` render with
    ``shadow_taps=False`` / ``image_detail=False``; the defaults are True."""
    import facegeo.pipeline.render as render

    seen = []
    monkeypatch.setattr("facegeo.cli._run_reconstruct", lambda *a, **k: None)
    monkeypatch.setattr(render, "run_render",
                        lambda *a, **k: seen.append((k["shadow_taps"], k["image_detail"])) or
                        {"name": "v", "files": {"png": "v.png"}})
    view = ["render", str(tiny_scan), "--camera", "orbit:cam_left:15", "-q"]
    assert main(view + ["--no-shadow-taps"]) == 0
    assert main(view + ["--no-image-detail"]) == 0
    assert main(view) == 0
    assert seen == [(False, True), (True, False), (True, True)], seen


def test_atlas_and_project_are_the_cached_stages_later_commands_reuse(tiny_scan, capsys):
    """``facegeo atlas`` and ``facegeo project`` (default products folder) run the cached
    stages of ``facegeo reconstruct`` with their settings: a later ``facegeo fit`` reuses them
    (it rebuilt both: their manifests had no key). ``--out`` still runs a stage on its own."""
    assert main(["atlas", str(tiny_scan), "-q"]) == 0
    assert main(["project", str(tiny_scan), "-q"]) == 0
    out = capsys.readouterr().out
    assert "atlas      cached" in out and "project    ran" in out, out
    assert main(["fit", str(tiny_scan), "-q"]) == 0
    out = capsys.readouterr().out
    assert "atlas      cached" in out and "project    cached" in out, out
    assert main(["atlas", str(tiny_scan), "--out", str(tiny_scan.parent / "elsewhere"),
                 "--texels-per-mm", "0.5"]) == 0
    assert (tiny_scan.parent / "elsewhere" / "atlas" / "texels.npz").is_file()
    # a rig file is not a pipeline rig: the stage on its own (it was refused once routed)
    rig = tiny_scan / "ground_truth" / "rig.json"
    assert main(["project", str(tiny_scan), "--rig", str(rig), "--gt-lights", "4", "-q"]) == 0
    assert "project    " not in capsys.readouterr().out  # no pipeline stage line


def test_max_coarse_px_reaches_the_decode_stage(monkeypatch, tiny_scan):
    """``--max-coarse-px`` is the decode stage's setting (it had no flag); absent, no decode
    settings are sent, so the default runs' cache keys do not change."""
    import facegeo.pipeline.reconstruct as reconstruct

    seen = []
    monkeypatch.setattr(reconstruct, "run_reconstruct",
                        lambda *a, **k: seen.append(k.get("settings")) or [])
    monkeypatch.setattr("facegeo.cli._write_report", lambda out: None)
    assert main(["decode", str(tiny_scan), "--max-coarse-px", "16", "-q"]) == 0
    assert main(["reconstruct", str(tiny_scan), "-q"]) == 0
    assert seen == [{"decode": {"max_coarse_px": 16.0}}, None], seen


def test_render_loads_the_scan_once(monkeypatch, tiny_scan, capsys):
    """``facegeo render`` validates the scan once: its argument check, the stages up to the
    fit and the render share the loaded scan (it was loaded three times)."""
    import facegeo.capture.scan as scan_mod
    import facegeo.pipeline.reconstruct as reconstruct
    import facegeo.pipeline.render as render

    loads, got = [], []
    real = scan_mod.load_scan
    monkeypatch.setattr(scan_mod, "load_scan", lambda *a, **k: loads.append(a) or real(*a, **k))
    monkeypatch.setattr(reconstruct, "run_reconstruct",
                        lambda scan, **k: got.append(("reconstruct", scan, k["until"])) or [])
    monkeypatch.setattr("facegeo.cli._write_report", lambda out: got.append(("report", out)))
    monkeypatch.setattr(render, "run_render", lambda scan, **k: got.append(("render", scan)) or
                        {"name": "v", "files": {"png": "v.png"}})
    assert main(["render", str(tiny_scan), "--camera", "front", "-q"]) == 0
    assert len(loads) == 1
    assert [g[0] for g in got] == ["reconstruct", "report", "render"]
    assert isinstance(got[0][1], scan_mod.Scan) and got[2][1] is got[0][1]
    assert got[0][2] == "fit" and got[1][1] == tiny_scan / "out"
    assert str(tiny_scan / "out" / "views" / "v.png") in capsys.readouterr().out


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux procfs")
@pytest.mark.parametrize("out, words", [
    ("/proc/facegeo-bench", ["--out /proc/facegeo-bench", "cannot create it", "/proc",
                             "refuses new files", "writable"]),
    ("/proc/facegeo-bench/deeper", ["--out /proc/facegeo-bench/deeper", "cannot create it",
                                    "/proc, its nearest existing folder"]),
    ("/proc", ["--out /proc", "cannot write in this directory", "writable"]),
])
def test_bench_out_errors_name_the_path_and_what_is_wrong(out, words, capfd):
    """``facegeo bench --out /proc/foo`` said only "No such file or directory" (of a probe
    file in /proc): the line names the path given, the folder that refuses and why."""
    assert main(["bench", "vis", "--out", out]) == 2
    lines = _stderr_lines(capfd.readouterr().err)
    assert len(lines) == 1, lines
    for w in words:
        assert w in lines[0], (w, lines[0])
