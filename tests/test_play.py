"""``hapticrom play``: the scripted oblique path, a CSV tool path (and hostile ones), the
written history."""

from __future__ import annotations

import numpy as np
import pytest

import hapticrom.online as online
from hapticrom.online.play import HISTORY_COLUMNS, play, read_path, scripted_tips
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial


@pytest.fixture(scope="module")
def model(small_artifact):
    return online.load(small_artifact)


def test_the_scripted_path_presses_obliquely_slides_and_lifts(model):
    """Free at the start, in contact along the 2 mm slide at a constant depth, free at the
    end; the press comes in 30 degrees from the normal, and the slide follows the surface."""
    ticks = 1000
    tips = scripted_tips(model, ticks)
    sim = model.simulator()
    depths, contact = np.zeros(ticks), np.zeros(ticks, dtype=bool)
    for i, tip in enumerate(tips):
        sim.step_position(tip)
        depths[i], contact[i] = sim.depth, sim.in_contact
    assert not contact[0] and not contact[-1]
    slide = slice(int(0.3 * ticks) + 1, int(0.7 * ticks) - 1)
    assert contact[slide].all()
    target = 0.8 * model.trained_depth
    np.testing.assert_allclose(depths[slide], target, rtol=0.02)  # facets of the coarse mesh
    press = np.diff(tips[: int(0.3 * ticks)], axis=0).mean(axis=0)
    sim.step_position(tips[int(0.3 * ticks)])
    cosine = -press @ np.asarray(sim.contact_normal) / np.linalg.norm(press)
    assert abs(np.degrees(np.arccos(cosine)) - 30.0) < 3.0
    length = np.linalg.norm(np.diff(tips[slide], axis=0), axis=1).sum()
    assert 1.8 < length < 2.3  # 2 mm along the curved surface (at the tip's depth)


def test_the_scripted_path_fits_a_tool_wider_than_its_approach_height(model):
    """A sphere of 6 mm (the liver's tip is 10 mm): the rays that place the path start
    outside the sheet of the sphere's centres (they started 5 mm above the surface: inside
    it, so `hapticrom play` refused the liver model). The slide keeps the asked depth."""
    ticks = 400
    tips = scripted_tips(model, ticks, radius=6.0)
    sim = model.simulator(tool_radius=6.0)
    depths = np.zeros(ticks)
    for i, tip in enumerate(tips):
        sim.step_position(tip)
        depths[i] = sim.depth
    slide = depths[int(0.3 * ticks) + 1 : int(0.7 * ticks) - 1]
    np.testing.assert_allclose(slide, 0.8 * model.trained_depth, rtol=0.05)


def test_a_csv_path_is_played_and_its_history_written(model, tmp_path):
    tips = scripted_tips(model, 300)
    csv = tmp_path / "path.csv"
    rows = np.column_stack([np.arange(300) / 1000.0, tips])
    csv.write_text("t,x,y,z\n" + "\n".join(",".join(f"{v:.12g}" for v in r) for r in rows))
    summary = play(model.path, tip_path=csv, realtime=False, say=lambda _: None,
                   out=tmp_path / "history")  # fmt: skip
    history = np.loadtxt(tmp_path / "history.csv", delimiter=",", skiprows=1)
    header = (tmp_path / "history.csv").read_text().splitlines()[0]
    assert header == ",".join(HISTORY_COLUMNS) and history.shape == (300, len(HISTORY_COLUMNS))
    np.testing.assert_allclose(history[:, 1:4], tips, atol=1e-11)
    sim = model.simulator()
    expected = np.array([sim.step_position(t).copy() for t in tips])
    np.testing.assert_allclose(history[:, 4:7], expected, rtol=1e-8, atol=1e-15)
    assert summary["ticks"] == 300 and summary["max_force_n"] > 0
    assert (tmp_path / "history.png").stat().st_size > 1000


def test_the_scripted_path_with_friction_obeys_the_friction_law(model, tmp_path):
    """The oblique press and the slide with Coulomb friction (``play --friction``): at every
    tick in contact |F_t| <= mu_s F_n when stuck and = mu_d F_n when slipping; the slide
    slips; the press in at 30 degrees (tan 30 = 0.58 > mu_s) drags the tissue."""
    mu_s, mu_d = 0.4, 0.25
    summary = play(model.path, rate=1000.0, seconds=1.0, realtime=False, say=lambda _: None,
                   out=tmp_path / "rub", friction=(mu_s, mu_d))  # fmt: skip
    history = np.loadtxt(tmp_path / "rub.csv", delimiter=",", skiprows=1)
    fn, ft, slipping = history[:, 9], history[:, 10], history[:, 11] > 0
    touching = history[:, 8] > 0
    assert np.all(fn[touching] >= 0) and not ft[~touching].any()
    stuck = touching & ~slipping
    # (the CSV keeps 9 significant digits; test_friction checks the law to 1e-12)
    assert np.all(ft[stuck] <= mu_s * fn[stuck] * (1 + 3e-8) + 1e-15)
    np.testing.assert_allclose(ft[slipping], mu_d * fn[slipping], rtol=3e-8)
    ticks = len(history)
    slide = slice(int(0.35 * ticks), int(0.65 * ticks))
    assert slipping[slide].mean() > 0.5 and summary["slipping_ticks"] == slipping.sum()
    assert (ft[touching] > 0).mean() > 0.5
    play(model.path, rate=1000.0, seconds=1.0, realtime=False, say=lambda _: None,
         out=tmp_path / "smooth")  # fmt: skip
    frictionless = np.loadtxt(tmp_path / "smooth.csv", delimiter=",", skiprows=1)
    assert frictionless[:, 10].max() < 1e-12 * frictionless[:, 9].max()
    assert not frictionless[:, 11].any()


@pytest.mark.parametrize("friction", [(-0.1,), (0.2, 0.3), (np.nan,)])
def test_bad_friction_is_refused_before_the_loop(model, tmp_path, friction):
    with pytest.raises(InputError, match="friction"):
        play(model.path, seconds=0.01, realtime=False, say=lambda _: None,
             out=tmp_path / "bad", friction=friction)  # fmt: skip
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "text,message",
    [
        ("", "no rows"),
        ("t,x,y,z\n", "no rows"),
        ("0,1,2\n", "line 1: expected 4 finite numbers"),
        ("0,1,2,3\n0.1,1,2,nan\n", "line 2: expected 4 finite numbers"),
        ("0,1,2,3\n0.1,a,2,3\n", "line 2: expected 4 finite numbers"),
        ("0,1,2,3\n0.1,1,2,3,4\n", "line 2: expected 4 finite numbers"),
        ("0,1,2,3\n0,1,2,3\n", "line 2: times must increase"),
        ("# a comment\n0.2,1,2,3\n0.1,1,2,3\n", "line 3: times must increase"),
        ("-1,1,2,3\n", "line 1: times must increase from 0"),
        ("0,1,2,3\n1,1e9,2,3\n", "line 2: a coordinate beyond"),
        ("t,x,y,z\n0,1,2,3\nt,x,y,z\n", "line 3: expected 4 finite numbers"),
    ],
)
def test_a_bad_csv_path_is_refused_naming_the_line(tmp_path, text, message):
    path = tmp_path / "path.csv"
    path.write_text(text)
    with pytest.raises(InputError, match=message):
        read_path(path)


def test_a_missing_or_binary_path_is_refused(tmp_path):
    with pytest.raises(InputError, match="cannot read it"):
        read_path(tmp_path / "absent.csv")
    (tmp_path / "binary.csv").write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(InputError, match="cannot read it"):
        read_path(tmp_path / "binary.csv")


def test_comments_and_a_header_are_allowed(tmp_path):
    path = tmp_path / "path.csv"
    path.write_text("# from the device log\nt, x, y, z\n0,1,2,3  # start\n0.5,1,2,2.5\n")
    times, tips = read_path(path)
    np.testing.assert_array_equal(times, [0.0, 0.5])
    np.testing.assert_array_equal(tips, [[1, 2, 3], [1, 2, 2.5]])
