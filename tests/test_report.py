"""``hapticrom report``: the self-contained HTML report on a reduced model."""

from __future__ import annotations

import base64
import io
import json
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from hapticrom.cli import main
from hapticrom.report import SECTION_HEADINGS, write_report
from hapticrom.shared.artifact import read_artifact
from hapticrom.shared.errors import HapticromError

pytestmark = pytest.mark.serial

LATENCY_STEPS = 2000  # enough for a histogram; the default 20,000 is for real models
FIGURES_WITHOUT_ACCURACY = 5  # eigenvalues, load-displacement, latency, two surface views
EMBEDDED_PNG = re.compile(r'<img src="data:image/png;base64,([A-Za-z0-9+/=]+)"')


@pytest.fixture(scope="module")
def report(small_artifact, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("report")
    return write_report(small_artifact, out, latency_steps=LATENCY_STEPS)


def embedded_pngs(report: Path) -> list[bytes]:
    return [base64.b64decode(data) for data in EMBEDDED_PNG.findall(report.read_text())]


def assert_readable_figure(data: bytes) -> None:
    from matplotlib.image import imread

    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(data) > 10_000, f"a {len(data)}-byte PNG is too small to hold a figure"
    pixels = imread(io.BytesIO(data), format="png")
    assert pixels.ndim == 3 and min(pixels.shape[:2]) >= 300, pixels.shape
    assert pixels.std() > 0.05, "the figure is (nearly) blank"


def accuracy_json(path: Path, error_anm: float = 0.03, field_errors: bool = False) -> Path:
    """A small file in the layout of ``bench/accuracy.py --json`` (format 1): two positions,
    three depths; with ``field_errors``, the per-row field errors of ``hapticrom accuracy``.

    The POD-ANM column is off by ``error_anm`` (above its 2 % target); the curves by 1 %.
    Surface-field errors: 5 % (curves) and 4 % (ANM), above their 3 % target.
    """
    rows = []
    for position, point in enumerate([[0.5, -0.2, -0.02], [-0.9, 1.1, -0.15]]):
        for k, depth in enumerate([0.1, 0.2, 0.3]):
            f_fem = 0.01 * (k + 1)
            rows.append([position, point, depth, f_fem, 1.01 * f_fem, (1 + error_anm) * f_fem])
    summary = {
        "podi+curves": {"max_force_error": 0.01, "max_field_error": 0.05},
        "grassmann+curves": {"max_force_error": 0.012, "max_field_error": 0.07},
        "podi+anm": {"max_force_error": error_anm, "max_field_error": 0.04},
    }
    data = {"summary": summary, "rows": rows}
    if field_errors:  # position 1 has the worst field, 2 % (curves) and 2.5 % (ANM) elsewhere
        data["field_errors"] = [[0.05, 0.04] if r[0] == 1 else [0.02, 0.025] for r in rows]
    path.write_text(json.dumps(data))
    return path


def test_every_section_is_there(report):
    html = report.read_text()
    for heading in SECTION_HEADINGS:
        assert f"<h2>{heading}</h2>" in html, heading
    # how to get the held-out errors: the command, not a script of the repository
    assert "mpirun -n 2 hapticrom accuracy" in html and "--json" in html
    assert "bench/accuracy.py" not in html


def test_figures_are_embedded_saved_and_readable(report):
    pngs = embedded_pngs(report)
    assert len(pngs) == FIGURES_WITHOUT_ACCURACY
    saved = {p.read_bytes() for p in report.parent.glob("*.png")}
    assert saved == set(pngs)
    for data in pngs:
        assert_readable_figure(data)


def test_dataset_table_lists_every_dataset(report, small_artifact):
    html = report.read_text()
    artifact = read_artifact(small_artifact)
    for group, arrays in artifact.groups.items():
        for name, array in arrays.items():
            row = f"<td>{group}</td><td>{name}</td><td>{array.shape}</td><td>{array.dtype}</td>"
            assert row in html, row
            assert f'<td class="num">{array.nbytes:,}</td>' in html


def test_held_out_errors_from_an_accuracy_file(small_artifact, tmp_path):
    accuracy = accuracy_json(tmp_path / "accuracy.json")
    report = write_report(small_artifact, tmp_path / "out", accuracy, latency_steps=500)
    html = report.read_text()
    assert len(embedded_pngs(report)) == FIGURES_WITHOUT_ACCURACY + 1
    assert_readable_figure((tmp_path / "out" / "held-out-error.png").read_bytes())
    # summary: the curves meet their 5 % target, the series miss their 2 % one; both miss
    # the 3 % target of the surface field, and the report says so
    assert (
        '<td>podi+curves</td><td class="num">1.00</td><td class="num">5</td><td>met</td>'
        '<td class="num">5.00</td><td class="num">3</td><td>missed</td>'
    ) in html
    assert (
        '<td>podi+anm</td><td class="num">3.00</td><td class="num">2</td><td>missed</td>'
        '<td class="num">4.00</td><td class="num">3</td><td>missed</td>'
    ) in html
    assert "force 2 % for POD-ANM series and 5 % for interpolated full-order curves" in html
    assert "surface field 3 % for every response" in html
    # one row per held-out position, with the worst error of each response
    assert html.count('<td class="num">1.00</td><td class="num">3.00</td></tr>') == 2


def test_field_errors_per_position_and_field_verdicts(small_artifact, tmp_path, monkeypatch):
    """Format 2 (``hapticrom accuracy --json``): field columns per position; a field error
    within the target is "met". The targets come from hapticrom.shared.accuracy."""
    import hapticrom.shared.accuracy

    accuracy = accuracy_json(tmp_path / "accuracy.json", field_errors=True)
    data = json.loads(accuracy.read_text())
    data["summary"]["podi+curves"]["max_field_error"] = 0.05
    data["summary"]["podi+anm"]["max_field_error"] = 0.04
    data["summary"]["grassmann+curves"]["max_field_error"] = 0.01
    accuracy.write_text(json.dumps(data))
    monkeypatch.setitem(hapticrom.shared.accuracy.TARGETS["field"], "anm", 0.05)
    report = write_report(small_artifact, tmp_path / "out", accuracy, latency_steps=500)
    html = report.read_text()
    assert '<td>grassmann+curves</td><td class="num">1.20</td><td class="num">5</td><td>met' in html
    assert '<td class="num">1.00</td><td class="num">3</td><td>met</td></tr>' in html
    assert '<td class="num">5.00</td><td class="num">3</td><td>missed</td></tr>' in html
    assert '<td class="num">4.00</td><td class="num">5</td><td>met</td></tr>' in html
    assert "max field error podi+anm (%)" in html
    # per position: worst force error of each response, then worst field error of each
    assert '<td class="num">1.00</td><td class="num">3.00</td><td class="num">2.00</td>' in html
    assert '<td class="num">1.00</td><td class="num">3.00</td><td class="num">5.00</td>' in html
    assert_readable_figure((tmp_path / "out" / "held-out-error.png").read_bytes())


def test_outside_positions_dotted_and_extrapolated_steps_open(tmp_path):
    """Format 3: a position clamped to the trained region is drawn dotted, a step beyond
    the solved depth with an open marker; the rest solid with filled markers."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from hapticrom.report.figures import _plot_errors
    from hapticrom.report.heldout import read_accuracy

    path = accuracy_json(tmp_path / "accuracy.json", field_errors=True)
    data = json.loads(path.read_text())
    data["outside_trained_region"] = [1]
    data["beyond_trained_depth"] = [[r[0] == 1 and r[2] > 0.25] * 2 for r in data["rows"]]
    path.write_text(json.dumps(data))
    results = read_accuracy(path)
    assert results.outside == {1} and results.beyond.sum() == 2
    ax = Figure().add_subplot()
    _plot_errors(ax, results, 100 * results.errors, "force")
    styles = [(line.get_linestyle(), line.get_marker(), line.get_markerfacecolor(),
               len(line.get_xdata())) for line in ax.lines]  # fmt: skip
    dotted = [s for s in styles if s[0] == ":" and s[3] == 3]
    assert len(dotted) == 2  # position 1, one line per response
    assert sum(s[1] == "o" and s[2] == "none" and s[3] == 1 for s in styles) == 2
    labels = [line.get_label() for line in ax.lines]
    assert "outside the trained region" in labels and "beyond the solved depth" in labels


def test_the_field_panel_goes_logarithmic_where_one_response_is_far_off():
    """PODI's field 50-220 % off beside the compliance surface's 1-2 %: a log axis, so that
    both show; errors within ten times the target keep a linear axis from zero."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    from hapticrom.report.figures import _log_if_spread

    far, near = Figure().add_subplot(), Figure().add_subplot()
    _log_if_spread(far, np.array([[1.0, 50.0], [2.0, 220.0], [np.nan, 0.0]]), "field")
    _log_if_spread(near, np.array([[1.0, 25.0], [2.0, 3.0]]), "field")
    assert far.get_yscale() == "log" and far.get_ylim() == pytest.approx((0.5, 440.0))
    assert near.get_yscale() == "linear"


@pytest.mark.parametrize(
    "content, message",
    [
        ("{not json", "is not JSON"),
        ('{"summary": {}}', "has no 'rows'"),
        (
            '{"summary": {"podi+curves": {}}, "rows": [[0, [0, 0, 0], 0.1, 0.01, 0.01]], '
            '"field_errors": [[0.1, 0.2]]}',
            "'field_errors' must have one row per row and one column per PODI combination",
        ),
        (
            '{"summary": {"podi+curves": {}}, "rows": [[0, [0, 0, 0], 0.1, 0.01, 0.01]], '
            '"beyond_trained_depth": [[1]]}',
            "'beyond_trained_depth' must hold one row of 1 booleans per row",
        ),
        (
            '{"summary": {"podi+curves": {}}, "rows": [[0, [0, 0, 0], 0.1, 0.01, 0.01]], '
            '"outside_trained_region": [true]}',
            "'outside_trained_region' must be a list of position indices",
        ),
    ],
)
def test_bad_accuracy_file_is_named(small_artifact, tmp_path, content, message):
    bad = tmp_path / "bad.json"
    bad.write_text(content)
    with pytest.raises(HapticromError, match=message):
        write_report(small_artifact, tmp_path / "out", bad)


def test_missing_artifact_is_a_clear_error(tmp_path, capsys):
    missing = tmp_path / "nope.h5"
    with pytest.raises(HapticromError, match="not found"):
        write_report(missing, tmp_path / "out")
    assert main(["report", str(missing), "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("hapticrom: error: ") and "not found" in err[0]
    assert not (tmp_path / "out").exists()


def test_without_matplotlib_says_what_to_install(small_artifact, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` now fails
    with pytest.raises(HapticromError, match="pip install matplotlib") as error:
        write_report(small_artifact, tmp_path / "out")
    assert "pip install 'hapticrom[report]'" in str(error.value)


def test_report_import_path_imports_no_finite_element_stack(small_artifact, tmp_path):
    """Everything ``hapticrom report`` imports, up to the runtime's answers: nothing of the
    offline trainer (DOLFINx, PETSc, MPI, gmsh, hapticrom.offline)."""
    code = textwrap.dedent(
        f"""
        import sys
        import hapticrom.cli, hapticrom.report
        from hapticrom.report import content, figures, heldout, page, surface, timing
        from hapticrom.cli import build_parser
        from hapticrom.cli.parser import parse
        args, petsc = parse(build_parser(), ["report", {str(small_artifact)!r}, "--out", "x"])
        assert args.command == "report" and petsc == []
        from hapticrom.online.model import load
        model = load({str(small_artifact)!r})
        content.summary_rows(model), content.deformed_surface(model, 0)
        timing.step_latencies_us(model, 0, 10)
        offline = ("dolfinx", "petsc4py", "slepc4py", "mpi4py", "ufl", "basix", "ffcx", "gmsh")
        bad = [m for m in sys.modules if m.split(".")[0] in offline]
        bad += [m for m in sys.modules if m.startswith("hapticrom.offline")]
        print(sorted(bad) or "clean")
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=600
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == "clean"


def test_report_modules_import_nothing_from_offline():
    """The source says so too: no ``hapticrom.offline`` import anywhere in the report."""
    import hapticrom.report

    imports = re.compile(
        r"^\s*(from hapticrom(\.offline| import offline)|import hapticrom\.offline)"
    )
    for path in Path(hapticrom.report.__file__).parent.glob("*.py"):
        lines = [line for line in path.read_text().splitlines() if imports.match(line)]
        assert not lines, (path, lines)


def test_command_runs_without_the_offline_stack(small_artifact, tmp_path):
    """Like the other online commands, the report never imports the finite-element stack."""
    code = textwrap.dedent(
        """
        import sys, importlib.abc
        BLOCKED = ("dolfinx", "petsc4py", "slepc4py", "mpi4py", "ufl", "basix", "ffcx", "gmsh")
        class Block(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name.split(".")[0] in BLOCKED or name.startswith("hapticrom.offline"):
                    raise ModuleNotFoundError(f"No module named {name!r}", name=name)
        sys.meta_path.insert(0, Block())
        from hapticrom.cli import main
        sys.exit(main(sys.argv[1:]))
        """
    )
    out = tmp_path / "out"
    proc = subprocess.run(
        [
            sys.executable,
            "-c",
            code,
            "report",
            str(small_artifact),
            "--out",
            str(out),
            "--latency-steps",
            "500",
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == f"wrote {out / 'report.html'}"
    assert (out / "report.html").is_file()


def test_physics_sanity_of_the_training_is_reported(report, small_artifact):
    """The small HGO model (0.3 mm on the coarse cornea) is physical: nothing flagged."""
    sanity = read_artifact(small_artifact).attrs["sanity"]
    assert sanity["flagged"] == [] and sanity["checked"] == 5
    html = report.read_text()
    assert "No training position flagged (5 checked)." in html
    assert "smallest J = det F" in html and "largest compression" in html


def test_flagged_sanity_is_shown_escaped_and_malformed_values_never_trusted():
    from hapticrom.report import flagged_rows, sanity_rows

    sanity = {
        "positions": 2,
        "worst": {
            "compression": {"value": 0.88, "position": 0, "step": 10, "load_factor": 1.0},
            "j_min": {"value": "<script>", "position": 1},
            "inverted": "not a dict",
        },
        "flagged": [{"position": 0, "kinds": ["compression"], "messages": ["88 %"]}, "junk"],
        "suggestion": "try law = <b>neo-hookean</b>",
    }
    rows = dict((label, (value, where)) for label, value, where in sanity_rows(sanity))
    assert rows["largest compression (1 - smallest stretch)"] == (
        "88%",
        "position 0, step 10, load_factor 1.0",
    )
    assert rows["smallest J = det F"][0] == "?"
    assert flagged_rows(sanity) == [("0", "compression", "88 %")]
