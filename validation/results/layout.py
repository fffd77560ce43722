"""Every path of a run directory (``mcillum validate --out DIR``), in one place.

    DIR/results.json                    the run's records (json_io.py)
    DIR/results.csv, DIR/summary.md     for spreadsheets, CI logs and pull requests
    DIR/images/<scene>/                 reference, one render and the mean per estimator
    DIR/images/<scene>/display/         the speed stage's equal-time images
    DIR/failures/<case>/                reference, median- and worst-error renders
    DIR/renders/<id>/<file>.npz         kept renders: a re-run loads them (resumes)
    DIR/report/index.html               the report, one self-contained page

Functions that name a folder create it only where they say so.
"""

from __future__ import annotations

import os


def results_json(run_dir: str) -> str:
    return os.path.join(run_dir, "results.json")


def results_csv(run_dir: str) -> str:
    return os.path.join(run_dir, "results.csv")


def summary_md(run_dir: str) -> str:
    return os.path.join(run_dir, "summary.md")


def report_html(run_dir: str) -> str:
    return os.path.join(run_dir, "report", "index.html")


def images_dir(run_dir: str, scene_id: str) -> str:
    """A scene comparison's images."""
    return os.path.join(run_dir, "images", scene_id)


def display_dir(run_dir: str, scene_id: str) -> str:
    """The speed stage's images of a scene, at its display resolution."""
    return os.path.join(images_dir(run_dir, scene_id), "display")


def case_dir(run_dir: str, case_id: str) -> str:
    """A failure case's evidence images."""
    return os.path.join(run_dir, "failures", case_id)


def kept_renders(run_dir: str, run_id: str, name: str) -> str:
    """A set of kept renders (or the speed stage's timings) of a scene run
    or failure case."""
    return os.path.join(run_dir, "renders", run_id, f"{name}.npz")


def made(path: str) -> str:
    """``path``, a folder, after creating it."""
    os.makedirs(path, exist_ok=True)
    return path
