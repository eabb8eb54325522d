"""Tool paths driven through the runtime as a servo loop would (``hapticrom play``).

Position in, force out: each servo tick hands the tool tip's centre to
``step_position`` and gets the force back, paced in real time (busy waiting, like
a servo thread) or as fast as possible. The path is the built-in scripted one
(:func:`scripted_tips`: approach, press at 30 degrees from the normal, slide 2 mm
across the centre of the trained region following the curvature, lift) or a CSV
file of the tip's positions over time (:func:`read_path`). The history (tip, force,
depth, contact) can be written as CSV and drawn.
"""

from __future__ import annotations

import math
import os
import stat
import time
from array import array
from collections.abc import Callable
from pathlib import Path

import numpy as np

from hapticrom.online import proxy
from hapticrom.online.model import load
from hapticrom.shared.errors import InputError

MAX_PATH_ROWS = 3_600_000  # an hour at 1 kHz
MAX_PATH_SECONDS = 3600.0  # an hour: a longer path would pace a real-time loop for longer
MAX_LINE = 4096  # characters in one line of a tool path, comment included
MAX_PATH_BYTES = 100 * MAX_PATH_ROWS  # 360 MB: an hour of rows of 100 characters
MAX_COORDINATE = 1e4  # mm: a tip 10 m away is a unit mistake, not a path
HISTORY_COLUMNS = ("t_s", "x_mm", "y_mm", "z_mm", "fx_n", "fy_n", "fz_n", "depth_mm", "contact",
                   "normal_n", "tangential_n", "slipping")  # fmt: skip


def tool_path(model, ticks: int, depth_fraction: float = 0.8):
    """Contact points (mm) and depths (mm) of press (25 %), slide (50 %), release (25 %)
    along a straight line through the plan view (the contact-point path of ``export``)."""
    chart = model.plan_points
    centre = chart.mean(axis=0)
    half = 0.35 * (chart[:, 0].max() - chart[:, 0].min())
    t = np.linspace(0.0, 1.0, ticks)
    x = np.where(t < 0.25, -half, np.where(t > 0.75, half, -half + 2 * half * (t - 0.25) / 0.5))
    depth_max = depth_fraction * model.trained_depth
    depth = np.where(t < 0.25, t / 0.25, np.where(t > 0.75, (1 - t) / 0.25, 1.0)) * depth_max
    points = model.plan_origin + np.column_stack([centre[0] + x, np.full(ticks, centre[1])]) @ (
        model.plan_axes
    )
    return points, depth


def sheet_point(sheet: np.ndarray, p, direction) -> tuple[np.ndarray, np.ndarray]:
    """Where the ray from p along ``direction`` (unit) first enters the offset sheet, and
    the sheet's blended unit normal there (mm). ValueError if it misses the sheet."""
    p, direction = np.asarray(p, dtype=np.float64), np.asarray(direction, dtype=np.float64)
    state = np.zeros(proxy.state_size(sheet))
    reach = 2.0 * float(np.ptp(proxy.sheet_views(sheet)[0].reshape(-1, 3), axis=0).max()) + 1.0
    end = p + reach * direction
    t, s = proxy.first_crossing(p, (end[0], end[1], end[2]), sheet, state)
    if t < 0:
        raise ValueError(f"the ray from {p.round(3).tolist()} mm misses the loadable surface")
    x = p + s * (end - p)
    views = proxy.sheet_views(sheet)
    offset, tri = views[0].reshape(-1, 3), views[3].reshape(-1, 3).astype(np.int64)
    a, b, c = offset[tri[t]]
    weights = np.linalg.lstsq(np.column_stack([b - a, c - a]), x - a, rcond=None)[0]
    _, _, n = proxy.proxy_frame(sheet, t, 1.0 - weights.sum(), weights[0], weights[1])
    return x, np.array(n)


def scripted_tips(model, ticks: int, radius: float | None = None, depth_fraction: float = 0.8,
                  angle_deg: float = 30.0, slide_mm: float = 2.0) -> np.ndarray:  # fmt: skip
    """Tip centres (ticks, 3) mm of the built-in path: approach from 1 mm above and press
    along a line ``angle_deg`` from the normal (30 %), slide ``slide_mm`` across the
    centre of the trained region at a constant depth along the normal, following the
    curvature (40 %), lift along the normal (30 %). The depth is ``depth_fraction`` of the
    trained depth; the sphere's radius is the training's unless given."""
    radius = model.contact_radius if radius is None else radius
    sheet = model.contact_sheet(radius)
    centre = model.sample_points[int(np.argmin(np.linalg.norm(model.plan_points, axis=1)))]
    normal = model.sample_normals[int(np.argmin(np.linalg.norm(model.plan_points, axis=1)))]
    along = model.plan_axes[0] - (model.plan_axes[0] @ normal) * normal
    along /= np.linalg.norm(along)
    depth = depth_fraction * model.trained_depth
    above = radius + 5.0  # mm: outside the offset sheet (the sphere's centres), as rays start
    n_press, n_slide = int(0.3 * ticks), int(0.4 * ticks)
    n_lift = ticks - n_press - n_slide
    slide = []
    for s in np.linspace(-0.5 * slide_mm, 0.5 * slide_mm, max(n_slide, 2)):
        x, n = sheet_point(sheet, centre + s * along + above * normal, -normal)
        slide.append(x - depth * n)
    slide = np.array(slide)
    _, n_a = sheet_point(sheet, slide[0] + above * normal, -normal)
    angle = math.radians(angle_deg)
    inward = -(math.cos(angle) * n_a + math.sin(angle) * along)  # pressing towards the slide
    start = slide[0] - (depth + 1.0) / math.cos(angle) * inward
    press = start + np.linspace(0.0, 1.0, n_press)[:, None] * (slide[0] - start)
    _, n_b = sheet_point(sheet, slide[-1] + above * normal, -normal)
    lift = slide[-1] + np.linspace(0.0, depth + 1.0, n_lift)[:, None] * n_b
    return np.vstack([press, slide[:n_slide], lift])[:ticks]


def read_path(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """(times (N,) s, tip centres (N, 3) mm) of a CSV file with columns t, x, y, z (a
    header line ``t,x,y,z`` optional; ``#`` comments; UTF-8 with or without a byte-order
    mark; any line ends). Refused with one InputError naming the line: not 4 plain (ASCII)
    numbers, not finite, times not increasing from >= 0, a coordinate beyond 10 m, a line
    longer than MAX_LINE characters; or naming the file: not a regular file, larger than
    MAX_PATH_BYTES, more than an hour of rows at 1 kHz or longer than an hour, empty. The
    file is read line by line into one array (about 40 bytes a row)."""
    path = Path(path)
    _check_path_file(path)
    try:
        with open(path, encoding="utf-8-sig", newline=None) as f:  # universal newlines only
            data, lines = _path_rows(path, f)
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"tool path {path}: cannot read it ({exc})") from None
    if len(data) == 0:
        raise InputError(f"tool path {path}: no rows (columns t, x, y, z)")
    steps = np.diff(data[:, 0])
    if data[0, 0] < 0 or np.any(steps <= 0):
        bad = 0 if data[0, 0] < 0 else int(np.argmax(steps <= 0)) + 1
        raise InputError(
            f"tool path {path}, line {lines[bad]}: times must increase from 0 or later "
            f"(t = {data[bad, 0]:g} s)"
        )
    if data[-1, 0] - data[0, 0] > MAX_PATH_SECONDS:
        bad = int(np.argmax(data[:, 0] - data[0, 0] > MAX_PATH_SECONDS))
        raise InputError(
            f"tool path {path}, line {lines[bad]}: t = {data[bad, 0]:g} s is more than "
            f"{MAX_PATH_SECONDS:g} s after the first row (a path of at most an hour)"
        )
    return data[:, 0].copy(), np.ascontiguousarray(data[:, 1:])


def _check_path_file(path: Path) -> None:
    """InputError unless ``path`` is a regular file of at most MAX_PATH_BYTES: a FIFO or a
    device (/dev/zero) would block or never end."""
    try:
        info = path.stat()
    except OSError as exc:
        raise InputError(f"tool path {path}: cannot read it ({exc.strerror or exc})") from None
    if not stat.S_ISREG(info.st_mode):
        raise InputError(f"tool path {path}: cannot read it (not a regular file)")
    if info.st_size > MAX_PATH_BYTES:
        raise InputError(
            f"tool path {path}: {info.st_size:,} bytes, more than {MAX_PATH_BYTES:,} (an hour "
            "of rows at 1 kHz)"
        )


def _path_rows(path: Path, f) -> tuple[np.ndarray, array]:
    """The rows (N, 4) of an open tool path and the line number of each."""
    values, lines = array("d"), array("q")
    number, size = 0, 0
    while line := f.readline(MAX_LINE + 1):
        number, size = number + 1, size + len(line)
        if len(line) > MAX_LINE or size > MAX_PATH_BYTES:  # (the file grew while read)
            raise InputError(
                f"tool path {path}, line {number}: longer than {MAX_LINE} characters"
                if len(line) > MAX_LINE
                else f"tool path {path}: more than {MAX_PATH_BYTES:,} bytes"
            )
        line = line.split("#", 1)[0].strip()
        if not line or (not lines and line.replace(" ", "").lower() == "t,x,y,z"):
            continue
        if len(lines) >= MAX_PATH_ROWS:
            raise InputError(f"tool path {path}: more than {MAX_PATH_ROWS:,} rows")
        values.extend(_path_row(path, number, line))
        lines.append(number)
    return np.frombuffer(values, dtype=np.float64).reshape(-1, 4), lines


def _path_row(path: Path, number: int, line: str) -> list[float]:
    fields = line.split(",")
    try:  # plain numbers only: float() also takes "1_000" and other scripts' digits
        values = [float(f) for f in fields] if line.isascii() and "_" not in line else []
    except ValueError:
        values = []
    if len(values) != 4 or not all(math.isfinite(v) for v in values):
        raise InputError(
            f"tool path {path}, line {number}: expected 4 finite numbers t, x, y, z "
            f"(s, mm), got {line[:80]!r}"
        )
    if max(abs(v) for v in values[1:]) > MAX_COORDINATE:
        raise InputError(
            f"tool path {path}, line {number}: a coordinate beyond {MAX_COORDINATE:g} mm "
            "(the path is in mm)"
        )
    return values


def play(
    path: str | Path,
    rate: float = 1000.0,
    seconds: float = 3.0,
    interpolation: str | None = None,
    realtime: bool = True,
    say: Callable[[str], None] = print,
    tip_path: str | Path | None = None,
    out: str | Path | None = None,
    friction: tuple[float, ...] | None = None,
) -> dict:
    """Drive the scripted path (``rate`` Hz for ``seconds``) or the CSV ``tip_path`` through
    ``step_position`` of a simulator of the artifact at ``path``, as a servo loop would
    (paced in real time, or as fast as possible), reporting through ``say``. With ``out``
    (a path prefix) the history goes to OUT.csv and, with matplotlib, OUT.png. Returns
    the achieved rate, the physics' latencies and the peak force. ``friction``: the
    arguments of ``Simulator.set_friction`` (static[, dynamic[, tangential stiffness]]).
    InputError (before anything runs or is written) for a bad ``out``, ``tip_path``,
    ``rate``, ``seconds`` or ``friction``, or a model the scripted path cannot be placed on."""
    if out is not None:
        history_paths(out)  # refused now, not after an hour of servo loop
    if tip_path is None:
        ticks = _scripted_ticks(rate, seconds)
    else:
        times, tips = read_path(tip_path)
        what = f"{tip_path}: {len(times)} positions over {times[-1]:.3g} s"
    model = load(path)
    sim = model.simulator(interpolation)
    if friction is not None:
        sim.set_friction(*friction)
    if tip_path is None:
        try:
            times, tips = np.arange(ticks) / rate, scripted_tips(model, ticks)
        except ValueError as exc:  # the model's loadable surface is not under its centre
            raise InputError(
                f"{path}: the scripted path cannot be placed on this model ({exc}); give a "
                "tool path instead (--path)"
            ) from None
        what = "approach, press at 30 deg, slide 2 mm across the centre, lift"
    say(f"playing {model.describe()}")
    source = "the POD-ANM series" if sim.response == "anm" else "the stored full-order curves"
    pacing = "real time" if realtime else "free running"
    rubbing = "frictionless" if not sim.friction[0] else (
        "friction static {:g}, dynamic {:g}".format(*sim.friction[:2]))  # fmt: skip
    say(f"{what}; tip radius {sim.tool_radius:g} mm; {rubbing}; {pacing}; force from {source}")
    history, physics_ns, elapsed = _servo_loop(sim, times, tips, realtime, say)
    us = physics_ns / 1e3
    summary = {
        "ticks": len(times),
        "achieved_rate_hz": len(times) / elapsed,
        "physics_p50_us": float(np.percentile(us, 50)),
        "physics_p99_us": float(np.percentile(us, 99)),
        "physics_max_us": float(us.max()),
        "max_force_n": float(np.linalg.norm(history[:, 4:7], axis=1).max()),
        "max_rate_hz": 1e6 / float(np.percentile(us, 99)),
        "slipping_ticks": int(history[:, 11].sum()),
    }
    say(
        f"achieved {summary['achieved_rate_hz']:.0f} Hz over {elapsed:.2f} s; physics per tick "
        f"(step_position) p50 {summary['physics_p50_us']:.1f} us, p99 "
        f"{summary['physics_p99_us']:.1f} us, max {summary['physics_max_us']:.0f} us "
        f"(room for {summary['max_rate_hz']:.0f} Hz at p99); "
        f"peak force {summary['max_force_n']:.4f} N"
    )
    if out is not None:
        for written in write_history(history, out):
            say(f"wrote {written}")
    return summary


def _scripted_ticks(rate: float, seconds: float) -> int:
    """The scripted path's ticks: ``rate`` (Hz) x ``seconds``, 1 to MAX_PATH_ROWS."""
    ticks = rate * seconds if 0 < rate < math.inf and 0 < seconds < math.inf else 0.0
    if not 1 <= ticks <= MAX_PATH_ROWS:
        raise InputError(
            f"play: rate {rate!r} Hz x seconds {seconds!r} s must make 1 to {MAX_PATH_ROWS:,} "
            "servo ticks"
        )
    return int(ticks)


def _servo_loop(sim, times, tips, realtime: bool, say) -> tuple:
    """(history (N, 12): t, tip, force, depth, contact, the force's normal and tangential
    parts, slipping; physics time per tick (ns); seconds in all) of the loop."""
    ticks = len(times)
    history = np.zeros((ticks, len(HISTORY_COLUMNS)))
    history[:, 0], history[:, 1:4] = times, tips
    physics_ns = np.zeros(ticks, dtype=np.int64)
    clock = time.perf_counter
    start = clock()
    for i in range(ticks):
        if realtime:
            while clock() < start + times[i] - times[0]:
                pass
        t0 = time.perf_counter_ns()
        force = sim.step_position(tips[i])
        physics_ns[i] = time.perf_counter_ns() - t0
        history[i, 4:7] = force
        history[i, 7], history[i, 8] = sim.depth, sim.in_contact
        normal = force @ sim.contact_normal if sim.in_contact else 0.0
        history[i, 9], history[i, 11] = normal, sim.slipping
        history[i, 10] = np.linalg.norm(force - normal * sim.contact_normal) if normal else 0.0
        if i % max(1, ticks // 15) == 0:
            state = "contact" if sim.in_contact else "free"
            say(
                f"  t {times[i]:6.3f} s  tip {np.round(tips[i], 3)} mm  {state:7s} depth "
                f"{sim.depth:.3f} mm  force {np.linalg.norm(force):.5f} N"
            )
    return history, physics_ns, clock() - start


def history_paths(out: str | Path) -> tuple[Path, Path]:
    """(OUT.csv, OUT.png) of the prefix ``out``, exactly as ``play --out`` names them; an
    InputError if the prefix names no file (empty, or ending in a separator: a directory),
    one of them is a directory, or their directory does not exist."""
    prefix = os.fspath(out)
    if not prefix or prefix.endswith(("/", os.sep)) or Path(prefix).name in ("", ".", ".."):
        raise InputError(
            f"play --out {prefix!r}: give a path prefix such as out/play (for out/play.csv "
            "and out/play.png)"
        )
    csv, png = Path(prefix + ".csv"), Path(prefix + ".png")
    for written in (csv, png):
        if written.is_dir():
            raise InputError(f"play --out {prefix}: {written} is a directory")
    if not csv.parent.is_dir():
        raise InputError(f"play --out {prefix}: directory {csv.parent} does not exist")
    return csv, png


def write_history(history: np.ndarray, out: str | Path) -> list[Path]:
    """OUT.csv (the columns of HISTORY_COLUMNS) and, if matplotlib is installed, OUT.png
    (force and depth over time; with friction, the tangential force against the cone's
    bound and the slipping ticks); the names as :func:`history_paths` gives them."""
    csv, png = history_paths(out)
    np.savetxt(csv, history, delimiter=",", header=",".join(HISTORY_COLUMNS), comments="",
               fmt="%.9g")  # fmt: skip
    written = [csv]
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return written
    rubbing = bool(history[:, 10].any())
    fig, axes = plt.subplots(3 if rubbing else 2, 1, sharex=True, figsize=(7, 7 if rubbing else 5))
    top, bottom = axes[0], axes[-1]
    for c, name in enumerate("xyz"):
        top.plot(history[:, 0], history[:, 4 + c], label=f"F{name}")
    top.plot(history[:, 0], np.linalg.norm(history[:, 4:7], axis=1), "k", label="|F|")
    top.set_ylabel("force on the tool (N)")
    top.legend(loc="upper left", ncol=4, fontsize=8)
    if rubbing:
        _friction_panel(axes[1], history)
    bottom.plot(history[:, 0], history[:, 7], "k")
    bottom.set_ylabel("depth (mm)")
    bottom.set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return [*written, png]


def _friction_panel(ax, history: np.ndarray) -> None:
    """The tangential force, and where the proxy slipped (shaded)."""
    t = history[:, 0]
    ax.plot(t, history[:, 10], "C3", label="|F_t|")
    ax.plot(t, history[:, 9], "k:", lw=0.8, label="F_n")
    ax.fill_between(t, 0, history[:, 10].max(), where=history[:, 11] > 0, color="C3",
                    alpha=0.15, lw=0, label="slipping")  # fmt: skip
    ax.set_ylabel("friction (N)")
    ax.legend(loc="upper left", ncol=3, fontsize=8)
