"""U23 defects 12–14 (parts): docs and help that say what the code does, `make bench` running what README cites,
the stick figures' colour key, examples/plot_convergence.py naming the file it looked for."""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from imugraph.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]


def _subparser(name: str):
    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    return sub.choices[name]


def _long_flags(parser) -> set[str]:
    return {o for a in parser._actions for o in a.option_strings if o.startswith("--") and o != "--help"}


# ---------------------------------------------------------------- (13) docs/stream.md's command line and timing row
def test_stream_doc_command_line_lists_every_flag_of_stream_help():
    text = (ROOT / "docs" / "stream.md").read_text(encoding="utf-8")
    block = text.split("```")[1]                       # the first code block: the command line
    assert block.lstrip().startswith("imugraph stream SESSION")
    in_doc = set(re.findall(r"--[a-z][a-z0-9-]*", block))
    flags = _long_flags(_subparser("stream"))
    assert {"--bootstrap-max-s", "--fixed-calibration", "--lag-solver", "--calib-json-end-graph",
            "--allow-gaps"} <= flags
    assert sorted(flags - in_doc) == [] and sorted(in_doc - flags) == []


def test_stream_doc_timing_row_names_the_bootstrap_span_and_note():
    text = (ROOT / "docs" / "stream.md").read_text(encoding="utf-8")
    row = next(ln for ln in text.splitlines() if ln.startswith("| `timing.json` |"))
    assert "`bootstrap_span_s`" in row and "`bootstrap_note`" in row
    source = (ROOT / "imugraph" / "graphs" / "stream_run.py").read_text(encoding="utf-8")
    assert 'timing["bootstrap_span_s"]' in source and 'timing["bootstrap_note"]' in source


# ---------------------------------------------------------------- (13) simulate --help about the .csv
def test_simulate_help_says_what_the_csv_holds(tmp_path):
    out_help = next(a.help for a in _subparser("simulate")._actions if "--out" in a.option_strings)
    assert main(["simulate", "--out", str(tmp_path / "s.csv"), "--duration", "10", "--rate", "20", "--quiet"]) == 0
    header = (tmp_path / "s.csv").read_text().splitlines()[0]
    assert "quat_w" in header                          # the file holds the true orientation ...
    assert "no truth" not in out_help and "quat_w" in out_help      # ... and the help says so


# ---------------------------------------------------------------- (12) make bench runs what README's table cites
def _status_table_scripts() -> set[str]:
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    start = lines.index("## Status at a glance")
    end = next(i for i in range(start + 1, len(lines)) if lines[i].startswith("## "))
    scripts = set()
    for ln in lines[start:end]:
        cells = ln.split(" | ")
        if ln.startswith("|") and len(cells) >= 5:
            scripts |= set(re.findall(r"benchmarks/([A-Za-z0-9_]+\.py)", cells[-2]))     # the command column
    return scripts


def _run_all():
    sys.path.insert(0, str(ROOT))
    from benchmarks import run_all

    return run_all


def test_run_all_runs_every_benchmark_of_the_status_table():
    run_all = _run_all()
    steps = {script for script, _, _ in run_all.STEPS}
    cited = _status_table_scripts()
    assert {"diagnose_body.py", "x19_swap.py", "speed.py"} <= cited          # the parse found the table
    assert sorted(cited - steps) == []
    assert "smooth_field.py" in steps                  # README's 2e text: smooth_field.py all --cache DIR


def test_run_all_repeated_scripts_write_distinct_outputs():
    """A script run several times (seeds, variants) writes each run to its own --out, or the last run wins."""
    run_all = _run_all()
    outs: dict[str, list] = {}
    for script, args, _ in run_all.STEPS:
        outs.setdefault(script, []).append(args[args.index("--out") + 1] if "--out" in args else None)
    assert {s: o for s, o in outs.items() if len(set(o)) != len(o)} == {}


def test_run_all_docstring_names_every_script_it_runs():
    """`run_all.py --help` prints the module docstring: its list of benchmarks is the list that runs."""
    run_all = _run_all()
    listed = set(re.findall(r"^    ([a-z0-9_]+\.py) ", run_all.__doc__, flags=re.M))
    assert sorted({script for script, _, _ in run_all.STEPS} - listed) == []


# ---------------------------------------------------------------- (14) stick figures: which colour is which side
def test_stick_figures_have_a_left_right_colour_key(tmp_path):
    from matplotlib.colors import to_rgba

    from imugraph.body.skeleton import lower_body
    from imugraph.io.body_figures import plot_stick_figures

    skel = lower_body()
    T = 20
    q = np.tile([1.0, 0, 0, 0], (T, len(skel.names), 1))
    pos = skel.forward_kinematics(q, np.tile([0, 0, 0.9], (T, 1)))
    fig = plot_stick_figures(tmp_path / "s.png", skel, np.arange(T) / 20.0, q, pos, count=2)
    assert len(fig.legends) == 1
    key = {t.get_text(): h.get_color() for t, h in zip(fig.legends[0].get_texts(), fig.legends[0].legend_handles)}
    assert "right side" in key and "left side" in key and to_rgba(key["right side"]) != to_rgba(key["left side"])
    drawn = {to_rgba(line.get_color()) for ax in fig.axes for line in ax.get_lines()}
    assert to_rgba(key["right side"]) in drawn and to_rgba(key["left side"]) in drawn


# ---------------------------------------------------------------- (14) plot_convergence's error names the file
@pytest.mark.parametrize("arg", ["missing_folder", "missing_folder/"])
def test_plot_convergence_error_names_calibration_history_json(tmp_path, capsys, arg):
    spec = importlib.util.spec_from_file_location("plot_convergence", ROOT / "examples" / "plot_convergence.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.main([str(tmp_path / arg)]) == 2
    err = capsys.readouterr().err
    assert str(tmp_path / "missing_folder" / "calibration_history.json") in err, err
    assert "FileNotFoundError" not in err
