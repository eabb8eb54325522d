"""What the artifact's validation costs at load, phase by phase, against the reader before it.

    python bench/artifact_load.py out/cornea-soft.h5 [--repeat 5]

Phases of ``hapticrom.online.load``: the envelope (read the file, whole-file
SHA-256), the structure (HDF5 parsed from memory, shapes, storage, per-dataset
digests), the value rules (``shared/artifact_rules.py``), the model set-up and
the kernel warm-up. The baseline is the reader of format 1.3 (git revision
``--baseline``, which checked dtypes, shapes and per-dataset digests only), run
on the same file in the same process: it reads the file through h5py directly.
Best of ``--repeat`` runs each (the page cache is warm after the first).
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def best(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def baseline_reader(revision: str):
    """``read_artifact`` of ``shared/artifact.py`` at ``revision``, or None without git."""
    try:
        source = subprocess.run(
            ["git", "-C", str(ROOT), "show", f"{revision}:shared/artifact.py"],
            capture_output=True, text=True, check=True,
        ).stdout  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return None
    path = Path(tempfile.mkdtemp()) / "artifact_baseline.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("artifact_baseline", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module.read_artifact


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("model", type=Path)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--baseline", default="425a6ed", help="git revision of the previous reader")
    args = p.parse_args()

    from hapticrom.online.model import ReducedModel, sweep
    from hapticrom.shared import artifact, artifact_rules, envelope

    path, r = args.model, args.repeat
    data = envelope.read_verified(path)

    def structure():
        return artifact.parse_verified(data, path, values=False)

    a = structure()
    rows = [
        ("envelope: read + whole-file SHA-256", best(lambda: envelope.read_verified(path), r)),
        ("structure, data, per-dataset digests", best(structure, r)),
        ("value rules (artifact_rules)", best(lambda: artifact_rules.check_values(a), r)),
        ("read_artifact (the three above)", best(lambda: artifact.read_artifact(path), r)),
        ("model set-up (ReducedModel)", best(lambda: ReducedModel.from_artifact(a), r)),
    ]
    model = ReducedModel.from_artifact(a)
    sweep(model)  # compiles or loads the kernels from the cache once
    rows.append(("sweep: every kernel over the region", best(lambda: sweep(model), r)))
    old = baseline_reader(args.baseline)
    if old is not None:
        rows.append((f"baseline: read_artifact at {args.baseline}", best(lambda: old(path), r)))
    print(f"{path}: {path.stat().st_size / 1e6:.1f} MB, best of {r}")
    for name, seconds in rows:
        print(f"  {name:42s} {1e3 * seconds:8.1f} ms")
    if old is not None:
        new, base = rows[3][1], rows[-1][1]
        print(f"  read_artifact / baseline: {new / base:.2f}x ({1e3 * (new - base):+.1f} ms)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
