"""``hapticrom report --held-out DIR``: the rendered surface against the full order.

The small campaign's own solves stand in for a held-out campaign: they are real full-order
solves on the model's mesh, at the training positions, where both the transported and the
PODI field must reproduce the full order (up to the POD truncation) -- and the choice of
the figure's step is checked against the held-out check's own comparison
(:func:`hapticrom.offline.accuracy.compare_position`), an independent implementation.
"""

from __future__ import annotations

import dataclasses
import io
import json
import re
import shutil

import numpy as np
import pytest

from hapticrom.cli import main
from hapticrom.online.model import load
from hapticrom.report.field_comparison import (
    PNG_NAME,
    PlanView,
    caption,
    field_figure,
    held_out_comparison,
    locate_on_sheet,
    write_field_comparison,
)
from hapticrom.report.page import _field_section
from hapticrom.shared.errors import InputError

pytestmark = pytest.mark.serial

# At a training position the runtime's field is the stored snapshot projected on the
# sample's POD modes (and, with the POD-ANM response, the series' coefficients): a few
# percent at most; measured on the small model: PODI 0.003 %, transport 0.3 %.
AT_TRAINING = 0.01
PERCENT = re.compile(r"(transport|compliance|PODI) (\S+) %")


@pytest.fixture(scope="module")
def model(small_artifact):
    return load(small_artifact)


@pytest.fixture(scope="module")
def work(small_campaign):
    return small_campaign[1].root


@pytest.fixture(scope="module")
def comparison(model, work):
    return held_out_comparison(model, work)


def test_training_position_is_reproduced_by_both_interpolations(comparison, model):
    assert model.chart is not None and comparison.runtime == "transport"
    assert comparison.panels == ("full order", "transport", "podi")
    assert comparison.fields.keys() == set(comparison.panels)
    for field in comparison.fields.values():
        assert field.shape == model.vertices.shape and np.isfinite(field).all()
    assert np.linalg.norm(comparison.fields["full order"]) > 0
    assert 0 < comparison.depth <= model.trained_depth
    for name in ("transport", "podi"):
        assert comparison.error(name) < AT_TRAINING, (name, comparison.error(name))


def test_the_step_shown_is_where_the_held_out_check_finds_podi_worst(comparison, model, work):
    from hapticrom.offline.accuracy import compare_position
    from hapticrom.offline.campaign.store import SnapshotStore

    store = SnapshotStore(work)
    response = "anm" if model.anm else "curves"
    podi, transport = f"podi+{response}", f"transport+{response}"
    worst = None
    for index in store.completed():
        data, attrs = store.read_position(index)
        steps, _ = compare_position(model, index, data, attrs)
        for k, step in enumerate(steps):
            if not step.beyond[podi] and (worst is None or step.field[podi] > worst[0]):
                worst = (step.field[podi], index, k, step.field[transport])
    error, index, k, transport_error = worst
    assert (comparison.index, comparison.step) == (index, k)
    assert comparison.error("podi") == pytest.approx(error, rel=1e-9)
    assert comparison.error("transport") == pytest.approx(transport_error, rel=1e-9)


def test_writes_a_readable_figure_and_its_caption(small_artifact, work, tmp_path):
    from matplotlib.image import imread

    path, caption = write_field_comparison(small_artifact, work, tmp_path / "out")
    assert path == tmp_path / "out" / PNG_NAME
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000
    pixels = imread(io.BytesIO(data), format="png")
    assert min(pixels.shape[:2]) >= 500 and pixels.std() > 0.05
    errors = PERCENT.findall(caption)
    assert len(errors) == 4, caption  # over the surface, then along the cross-section
    assert all(np.isfinite(float(value)) for _, value in errors)


def test_a_model_without_a_chart_shows_its_compliance_field(force_artifact, force_campaign):
    """No chart but contact fields: the runtime panel is "compliance" (the runtime's default
    then), in the fields, the caption, the figure's alt text and the page; at a training
    position its correction vanishes (the sample's own field less its blend, itself), so it
    reproduces the full order as PODI does. Neither chart nor fields: PODI alone. (The
    force-controlled campaign: only those get contact fields.)"""
    model, work = load(force_artifact), force_campaign[1].root
    comparison = held_out_comparison(model, work)
    assert model.contact_fields is not None
    no_chart = dataclasses.replace(model)
    no_chart.chart = None
    shown = held_out_comparison(no_chart, work)
    assert shown.runtime == "compliance"
    assert shown.panels == ("full order", "compliance", "podi")
    assert shown.fields.keys() == set(shown.panels)
    assert (shown.index, shown.step) == (comparison.index, comparison.step)  # PODI's worst
    np.testing.assert_array_equal(shown.fields["podi"], comparison.fields["podi"])
    assert shown.error("compliance") < AT_TRAINING, shown.error("compliance")
    text = caption(no_chart, shown)
    errors = PERCENT.findall(text)
    assert [name for name, _ in errors] == ["compliance", "PODI"] * 2, text
    assert "transport" not in text
    png = field_figure(no_chart, shown)
    assert "full order, compliance and PODI" in png.alt and len(png.data) > 10_000
    page = _field_section(text, work, png, no_chart)
    assert "<i>compliance</i> (the tool's linear dent at the contact" in page
    assert "transport" not in page

    bare = dataclasses.replace(model, contact_fields=None)
    bare.chart = None
    alone = held_out_comparison(bare, work)
    assert alone.runtime == "podi" and alone.panels == ("full order", "podi")
    assert alone.fields.keys() == {"full order", "podi"}
    errors = PERCENT.findall(caption(bare, alone))
    assert [name for name, _ in errors] == ["PODI", "PODI"]
    assert "full order and PODI in plan view" in field_figure(bare, alone).alt


def test_the_upper_sheet_is_read_where_two_overlap():
    """Two unit squares in plan view, one 1 mm above the other: points inside read the upper
    one, with weights that reproduce a linear function exactly; a point off both, none."""
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    plan = np.vstack([square, square])
    heights = np.repeat([0.0, 1.0], 4)
    triangles = np.array([[4, 5, 6], [4, 6, 7], [0, 1, 2], [0, 2, 3]])  # upper sheet first
    points = np.vstack([np.random.default_rng(7).uniform(0.0, 1.0, (25, 2)), [[1.5, 0.5]]])
    found, weights = locate_on_sheet(PlanView(plan, triangles, heights), points)
    assert found[-1] == -1
    assert set(found[:-1].tolist()) <= {0, 1}, "a point read the lower sheet"
    linear = 2.0 * plan[:, 0] - 3.0 * plan[:, 1] + 0.5
    read = np.einsum("ij,ij->i", weights[:-1], linear[triangles[found[:-1]]])
    np.testing.assert_allclose(read, 2.0 * points[:-1, 0] - 3.0 * points[:-1, 1] + 0.5)


def test_missing_directory_is_refused_and_nothing_written(small_artifact, tmp_path):
    missing = tmp_path / "no-such.heldout-8"
    with pytest.raises(InputError, match=re.escape(str(missing))):
        write_field_comparison(small_artifact, missing, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_directory_without_a_solved_position_is_refused(model, work, tmp_path):
    empty = tmp_path / "empty"
    (empty / "solves").mkdir(parents=True)
    shutil.copy(work / "manifest.json", empty / "manifest.json")
    with pytest.raises(InputError, match=f"{re.escape(str(empty))} holds no solved position"):
        held_out_comparison(model, empty)


def test_another_mesh_is_refused(model, work, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(work / "solves", other / "solves")
    manifest = json.loads((work / "manifest.json").read_text())
    manifest["mesh"]["sha256"] = "0" * 64
    (other / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(InputError, match="another mesh"):
        held_out_comparison(model, other)


def test_damaged_solve_is_refused_naming_it(model, work, tmp_path):
    import h5py

    damaged = tmp_path / "damaged"
    shutil.copytree(work, damaged)
    path = sorted((damaged / "solves").glob("position-*.h5"))[0]
    with h5py.File(path, "r+") as f:
        f["displacement"][0, 0] += 1.0  # the stored checksum no longer matches
    with pytest.raises(InputError, match=f"{re.escape(str(path))}.*checksum"):
        held_out_comparison(model, damaged)


def test_report_command_adds_the_section(small_artifact, work, tmp_path, capsys):
    out = tmp_path / "report"
    argv = ["report", str(small_artifact), "--out", str(out), "--latency-steps", "200"]
    assert main([*argv, "--held-out", str(work)]) == 0
    html = (out / "report.html").read_text()
    assert "<h2>Rendered surface vs full order at a held-out position</h2>" in html
    assert f'title="{PNG_NAME}"' in html and (out / PNG_NAME).stat().st_size > 10_000
    assert "Relative L2 error of the field over all surface vertices" in html

    refused = tmp_path / "refused"
    missing = tmp_path / "missing"
    argv = ["report", str(small_artifact), "--out", str(refused), "--held-out", str(missing)]
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(missing) in err[0] and "not found" in err[0]
    assert not refused.exists()
