"""Fuzz the artifact reader behind a re-sealed envelope: crafted bytes reach h5py.

Random damage never reaches h5py (the whole-file digest refuses it first; see
tests/test_artifact_hostile.py; ``--mode damage`` measures it here). A hostile writer
can re-seal, though, so by default this flips random bytes *after* the user
block (``--mode metadata``: only in the bytes HDF5 parses as structure, where a
crafted file would hit h5py's C code), re-seals the envelope, and loads each
file with ``hapticrom.online.load`` in a child process, counting:

  refused    ArtifactError (the promise)
  identical  loaded, every array equal to the original's
  changed    loaded with different values that passed every check
  uncaught   another exception escaped
  crashed    the child died of a signal (e.g. a segfault in HDF5's C code)
  hung       no answer within --timeout seconds

    python bench/fuzz_artifact.py out/cornea-soft.h5 --flips 1000 [--seed 1]

Exit status 1 if anything crashed, hung or escaped uncaught.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

# The 8-byte HDF5 signature after the user block: a flip there is not an HDF5 file at all (and
# seal() refuses to seal it), so the re-sealed modes leave it alone.
SIGNATURE = 8
OUTCOMES = ("refused", "identical", "changed", "uncaught", "crashed", "hung")


def metadata_bytes(source: Path) -> np.ndarray:
    """Offsets of the bytes HDF5 parses as structure: all after the user block but the
    datasets' contiguous data (a flip there only fails that dataset's digest)."""
    import h5py

    from hapticrom.shared.envelope import USERBLOCK

    mask = np.ones(source.stat().st_size, dtype=bool)
    mask[: USERBLOCK + SIGNATURE] = False

    def visit(_, obj):
        if isinstance(obj, h5py.Dataset) and obj.id.get_offset() is not None:
            start = obj.id.get_offset()
            mask[start : start + obj.id.get_storage_size()] = False

    with h5py.File(source, "r") as f:
        f.visititems(visit)
    return np.flatnonzero(mask)


def make_cases(source: Path, flips: int, seed: int, workdir: Path, mode: str) -> list[Path]:
    """Files with one random byte flipped: behind a re-sealed envelope (anywhere after the user
    block, or in the metadata only), or anywhere without re-sealing (damage)."""
    from hapticrom.shared.envelope import USERBLOCK, seal

    data = source.read_bytes()
    rng = np.random.default_rng(seed)
    reseal = mode != "damage"
    where = metadata_bytes(source) if mode == "metadata" else None
    cases = []
    for i in range(flips):
        damaged = bytearray(data)
        if where is not None:
            position = int(rng.choice(where))
        else:
            position = int(rng.integers(USERBLOCK + SIGNATURE if reseal else 0, len(data)))
        damaged[position] ^= int(rng.integers(1, 256))
        path = workdir / f"flip-{i:05d}-{position}.h5"
        path.write_bytes(bytes(damaged))
        if reseal:
            seal(path)
        cases.append(path)
    return cases


def child(source: str, cases: list[str], isolate: bool) -> None:
    """Load each case; print one JSON line per case (flushed, so a crash loses only its own)."""
    from hapticrom.online import load
    from hapticrom.shared.artifact import ArtifactError, read_artifact

    original = read_artifact(source)
    for case in cases:
        try:
            model = load(case, isolate=isolate)
            loaded = model.artifact.groups
            same = loaded.keys() == original.groups.keys() and all(
                k in loaded[g] and np.array_equal(loaded[g][k], v, equal_nan=True)
                for g, arrays in original.groups.items()
                for k, v in arrays.items()
            )  # an optional group whose name a flip changed is simply absent: "changed"
            outcome, detail = ("identical" if same else "changed"), ""
        except ArtifactError as exc:
            outcome, detail = "refused", str(exc).replace(case, "FILE")[:80]
        except BaseException as exc:  # noqa: BLE001 - what we are here to count
            outcome, detail = "uncaught", f"{type(exc).__name__}: {exc}"[:200]
        print(json.dumps({"case": case, "outcome": outcome, "detail": detail}), flush=True)


def run(source: Path, cases: list[Path], timeout: float, isolate: bool) -> dict[str, list]:
    """Children over the cases; a child that dies or stalls is replaced after its case."""
    results = {k: [] for k in OUTCOMES}
    pending = [str(c) for c in cases]
    while pending:
        proc = subprocess.Popen(
            [sys.executable, __file__, "--child", str(source), str(isolate), *pending],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True,
        )  # fmt: skip
        done = _collect(proc, timeout, results)
        if done < len(pending):  # the case after the last answered one crashed or hung
            outcome = "hung" if proc.returncode is None or proc.returncode == -9 else "crashed"
            results[outcome].append({"case": pending[done], "returncode": proc.returncode})
            done += 1
        pending = pending[done:]
    return results


def _collect(proc, timeout: float, results) -> int:
    import selectors

    sel = selectors.DefaultSelector()
    sel.register(proc.stdout, selectors.EVENT_READ)
    done, deadline = 0, time.monotonic() + timeout + 30  # the first case includes the imports
    while True:
        if not sel.select(timeout=max(0.0, deadline - time.monotonic())):
            proc.kill()
            proc.wait()
            proc.returncode = None
            return done
        line = proc.stdout.readline()
        if not line:
            proc.wait()
            return done
        record = json.loads(line)
        results[record["outcome"]].append(record)
        done += 1
        deadline = time.monotonic() + timeout


def main() -> int:
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        child(sys.argv[2], sys.argv[4:], isolate=sys.argv[3] == "True")
        return 0
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("artifact", type=Path)
    p.add_argument("--flips", type=int, default=1000)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--timeout", type=float, default=30.0, help="seconds per case")
    p.add_argument("--workdir", type=Path, default=None)
    p.add_argument("--json", type=Path, default=None, help="write every case's outcome here")
    p.add_argument(
        "--in-process",
        action="store_true",
        help="load(isolate=False): HDF5 parses in the loading process (measures what the "
        "isolation saves it from)",
    )
    p.add_argument(
        "--mode",
        choices=("resealed", "metadata", "damage"),
        default="resealed",
        help="resealed: flip after the user block and re-seal; metadata: the same, in HDF5's "
        "structure only; damage: flip anywhere, no re-seal (the envelope's job)",
    )
    args = p.parse_args()
    with tempfile.TemporaryDirectory(dir=args.workdir) as tmp:
        t0 = time.perf_counter()
        cases = make_cases(args.artifact, args.flips, args.seed, Path(tmp), args.mode)
        results = run(args.artifact.resolve(), cases, args.timeout, not args.in_process)
        seconds = time.perf_counter() - t0
    counts = {k: len(v) for k, v in results.items()}
    where = "in-process" if args.in_process else "isolated"
    print(f"{args.flips} byte flips ({args.mode}, {where}) of {args.artifact} ({seconds:.0f} s): "
          + ", ".join(f"{k} {n}" for k, n in counts.items()))  # fmt: skip
    reasons: dict[str, int] = {}
    for record in results["refused"]:
        key = record["detail"].split(" (")[0][:60]
        reasons[key] = reasons.get(key, 0) + 1
    for reason, n in sorted(reasons.items(), key=lambda kv: -kv[1])[:12]:
        print(f"  refused {n:5d}: {reason}")
    for outcome in ("changed", "uncaught", "crashed", "hung"):
        for record in results[outcome][:10]:
            print(f"  {outcome}: {record}")
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 1 if counts["uncaught"] + counts["crashed"] + counts["hung"] else 0


if __name__ == "__main__":
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    sys.exit(main())
