"""A bounded, seeded fuzz campaign over every input file the package reads: OctoMap ``.bt`` /
``.ot`` maps, ScanGraph ``.graph``, PCD, plain scan logs, batch manifests and configs.

Each case mutates a valid seed file (byte edits for binary formats; byte, token and line edits
for text) and checks that only documented outcomes come out:

* the library reader returns a valid result or raises its documented error naming the file
  (``MapFormatError`` / ``MemoryBudgetError`` for maps, ``ValueError`` for the others), with a
  one-line message;
* with ``--cli``, ``octomerge info`` and ``octomerge convert`` on a mutated map exit 0 or 1,
  print one ``octomerge CMD: error: ...`` line on failure, raise nothing, and leave no file
  beside the input but the requested output;
* nothing hangs (``--case-timeout`` seconds per case).

Run: ``python tests/fuzz_inputs.py --seconds 300 --seed 1 [--cli] [--save-failures DIR]``;
prints a table of cases / accepted / documented errors / failures per target. The default
test run keeps a small seeded slice of it (``tests/test_io_fuzz.py``).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import signal
import sys
import tempfile
import time
import traceback
import warnings
from collections import Counter
from pathlib import Path

import numpy as np

from octomerge_jax import morton
from octomerge_jax.budget import MemoryBudgetError, memory_budget
from octomerge_jax.cli import main as cli_main
from octomerge_jax.cli.manifest import read_manifest
from octomerge_jax.io import MapFormatError, load, to_bytes
from octomerge_jax.io.scans import read_scans, write_scan_graph, write_scan_log
from octomerge_jax.map import from_leaves
from octomerge_jax.pipeline import MergeConfig, config_to_dict, dumps_toml, load_config

TARGETS = ("bt", "ot", "graph", "pcd", "dat", "manifest", "toml", "json")
#: Memory budget for one case: a mutated header or body may claim a lot; the readers must
#: refuse it (MemoryBudgetError / MapTooLargeError) instead of allocating.
CASE_BUDGET = "512M"
SPECIAL_NUMBERS = [b"nan", b"-nan", b"inf", b"-inf", b"1e30", b"-1e30", b"1e308", b"5e-324", b"0",
                   b"-0", b"-5", b"1_0", b"0x10", b"99999999999999999999", b"", b"1e", b".", b"+"]


class Failure(Exception):
    """An undocumented outcome (wrong exception, multi-line message, file left behind)."""


# ----------------------------------------------------------------------------- seed files


def _sample_map():
    rng = np.random.default_rng(0)
    keys = np.unique(rng.integers(32768 - 30, 32768 + 30, size=(200, 3)), axis=0)
    codes = morton.keys_to_codes(keys.astype(np.uint16))
    coarse = morton.keys_to_codes(np.array([[32768 + 64] * 3], np.uint16))  # a depth-12 leaf
    codes = np.concatenate([codes, coarse])
    depths = np.concatenate([np.full(keys.shape[0], 16), [12]])
    values = rng.normal(size=codes.size).astype(np.float32)
    return from_leaves(codes, depths, values, 0.05)


def seed_files(folder: Path) -> dict[str, bytes]:
    """One valid file per target."""
    m = _sample_map()
    rng = np.random.default_rng(1)
    scans = [(rng.normal(size=(5, 3)), np.eye(4)), (rng.normal(size=(4, 3)), np.eye(4))]
    write_scan_graph(folder / "seed.graph", scans)
    write_scan_log(folder / "seed.dat", scans)
    pts = rng.normal(size=(6, 3)).astype(np.float32)
    pcd_head = ("VERSION 0.7\nFIELDS x y z intensity\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\n"
                "WIDTH 6\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 6\n")
    binary = np.concatenate([pts, np.ones((6, 1), np.float32)], 1).astype("<f4").tobytes()
    ascii_rows = "".join(f"{x:.4f} {y:.4f} {z:.4f} 1\n" for x, y, z in pts)
    cfg = MergeConfig()
    return {
        "bt": to_bytes(m, binary=True, header=True),
        "ot": to_bytes(m, binary=False, header=True),
        "graph": (folder / "seed.graph").read_bytes(),
        "dat": (folder / "seed.dat").read_bytes(),
        "pcd": (pcd_head + "DATA binary\n").encode() + binary,
        "pcd_ascii": (pcd_head + "DATA ascii\n" + ascii_rows).encode(),
        "manifest": b"map1,map2,output,x,y,z,roll,pitch,yaw\na.bt,b.bt,ab.bt,0.1,0,0,0,0,0.2\n"
                    b"b.bt,c.bt,bc.bt,1,2,3,0,0,1\n",
        "toml": dumps_toml(cfg).encode(),
        "json": (json.dumps(config_to_dict(cfg), indent=1) + "\n").encode(),
    }


# ----------------------------------------------------------------------------- mutations


def _byte_edit(buf: bytearray, rng, header_bias: bool) -> None:
    span = min(len(buf), 200) if header_bias else len(buf)
    pos = int(rng.integers(0, max(span, 1)))
    op = rng.integers(6)
    if op == 0:
        del buf[pos:]
    elif not buf:
        return
    elif op == 1:
        buf[min(pos, len(buf) - 1)] = int(rng.integers(256))
    elif op == 2:
        buf[min(pos, len(buf) - 1)] ^= 1 << int(rng.integers(8))
    elif op == 3:
        buf[pos:pos] = rng.bytes(int(rng.integers(1, 9)))
    elif op == 4:
        del buf[pos:pos + int(rng.integers(1, 17))]
    else:  # duplicate a chunk (repeated records / lines)
        n = int(rng.integers(1, 65))
        buf[pos:pos] = buf[pos:pos + n]


def _token_edit(buf: bytearray, rng) -> None:
    """Text formats: replace a token with a special number, drop / duplicate a line or
    token, add a BOM, CRLF line ends, or a very long token."""
    text = bytes(buf)
    lines = text.split(b"\n")
    op = rng.integers(7)
    i = int(rng.integers(len(lines)))
    if op <= 2:
        toks = lines[i].replace(b",", b" , ").split(b" ")
        if toks:
            j = int(rng.integers(len(toks)))
            toks[j] = SPECIAL_NUMBERS[int(rng.integers(len(SPECIAL_NUMBERS)))]
            lines[i] = b" ".join(toks).replace(b" , ", b",")
    elif op == 3:
        del lines[i]
    elif op == 4:
        lines.insert(i, lines[i])
    elif op == 5:
        lines[i] = lines[i] + b"x" * int(rng.choice([10, 5000, 70000]))
    else:
        lines = [b"\xef\xbb\xbf" + lines[0]] + lines[1:] if rng.random() < 0.5 else \
            [ln + b"\r" for ln in lines]
    buf[:] = b"\n".join(lines)


def mutate(data: bytes, target: str, rng) -> bytes:
    buf = bytearray(data)
    text = target in ("dat", "manifest", "toml", "json", "pcd_ascii")
    for _ in range(int(rng.integers(1, 4))):
        if text and rng.random() < 0.6:
            _token_edit(buf, rng)
        else:
            _byte_edit(buf, rng, header_bias=rng.random() < 0.5)
    return bytes(buf)


# ----------------------------------------------------------------------------- oracles


def _one_line(err: BaseException, path: Path) -> None:
    msg = str(err)
    if "\n" in msg:
        raise Failure(f"multi-line message: {msg[:200]!r}")
    if path.name not in msg:
        raise Failure(f"message does not name the file: {msg[:200]!r}")


def check_map(path: Path) -> str:
    """Strict, then (after a strict error) lenient reading, as ``--lenient`` does."""
    try:
        m = load(path)
    except (MapFormatError, MemoryBudgetError) as err:
        _one_line(err, path)
        try:
            m = load(path, strict=False)
        except (MapFormatError, MemoryBudgetError) as err:
            _one_line(err, path)
            return "error"
        _check_loaded(m)
        return "lenient"
    _check_loaded(m)
    return "ok"


def _check_loaded(m) -> None:
    lv = m.leaves()
    if lv.depths.size and (lv.depths.max() > 16 or np.isnan(lv.log_odds).any()):
        raise Failure("loaded an invalid map")
    from_leaves(lv.codes, lv.depths, lv.log_odds, m.resolution, check=True)
    if not (1e-6 <= m.resolution <= 1e6):
        raise Failure(f"loaded resolution {m.resolution!r}")


def check_scans(path: Path) -> str:
    try:
        scans = read_scans(path)
    except ValueError as err:
        _one_line(err, path)
        return "error"
    for s in scans:
        if s.points.ndim != 2 or s.points.shape[1] != 3 or not np.isfinite(s.pose).all():
            raise Failure("read an invalid scan")
    return "ok"


def check_manifest(path: Path) -> str:
    try:
        rows = read_manifest(path, path.parent / "out")
    except ValueError as err:
        _one_line(err, path)
        return "error"
    for r in rows:
        if not all(math.isfinite(v) for v in r.guess):
            raise Failure(f"row {r.index}: non-finite guess {r.guess}")
    return "ok"


def check_config(path: Path) -> str:
    try:
        load_config(path)
    except ValueError as err:
        _one_line(err, path)
        return "error"
    return "ok"


def check_cli(path: Path) -> str:
    """``info`` and ``convert`` on a mutated map: exit 0/1, one error line, no stray file."""
    before = set(path.parent.iterdir())
    out = path.with_name("converted" + (".ot" if path.suffix == ".bt" else ".bt"))
    outcomes = []
    for argv in (["info", str(path)], ["convert", str(path), str(out)]):
        stdout, stderr = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            rc = cli_main(argv)
        err = stderr.getvalue().strip()
        if rc not in (0, 1):
            raise Failure(f"{argv[0]}: exit code {rc}")
        if rc == 1 and (err.count("\n") or not err.startswith(f"octomerge {argv[0]}: error: ")):
            raise Failure(f"{argv[0]}: error output {err[:200]!r}")
        outcomes.append("ok" if rc == 0 else "error")
    after = set(path.parent.iterdir()) - before - {out}
    if after:
        raise Failure(f"files left beside the input: {sorted(p.name for p in after)}")
    if outcomes[1] == "error" and out.exists():
        raise Failure("convert failed but wrote its output")
    out.unlink(missing_ok=True)
    return outcomes[0]


CHECKS = {"bt": check_map, "ot": check_map, "graph": check_scans, "pcd": check_scans,
          "dat": check_scans, "manifest": check_manifest, "toml": check_config,
          "json": check_config}
SUFFIX = {"manifest": ".csv"}


# ----------------------------------------------------------------------------- campaign


class _Timeout(Exception):
    pass


def _alarm(signum, frame):
    raise _Timeout


def run_case(target: str, data: bytes, folder: Path, cli: bool, timeout: float) -> tuple[str, str]:
    """(outcome, detail): outcome ``ok`` / ``lenient`` (a map only ``--lenient`` reads) /
    ``error`` (documented) / ``fail``."""
    path = folder / f"case{SUFFIX.get(target, '.' + target)}"
    for p in folder.iterdir():
        p.unlink()
    path.write_bytes(data)
    use_alarm = timeout > 0 and hasattr(signal, "setitimer")
    if use_alarm:
        previous = signal.signal(signal.SIGALRM, _alarm)
        signal.setitimer(signal.ITIMER_REAL, timeout)
    try:
        with memory_budget(CASE_BUDGET), warnings.catch_warnings():
            warnings.simplefilter("error")  # as the test suite: a warning is a finding
            outcome = CHECKS[target](path)
            if cli and target in ("bt", "ot"):
                check_cli(path)
        return outcome, ""
    except Failure as err:
        return "fail", str(err)
    except _Timeout:
        return "fail", f"no result within {timeout:g} s"
    except Exception as err:  # an undocumented exception: the finding
        tb = traceback.extract_tb(err.__traceback__)[-1]
        return "fail", f"{type(err).__name__}: {str(err)[:160]} ({Path(tb.filename).name}:{tb.lineno})"
    finally:
        if use_alarm:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, previous)


def campaign(seed: int = 0, cases: int | None = None, seconds: float | None = None,
             targets=TARGETS, cli: bool = False, timeout: float = 20.0,
             save_failures: Path | None = None) -> dict:
    """Run mutated cases round-robin over ``targets`` until ``cases`` per target or
    ``seconds`` in all. Returns ``{target: Counter(ok=, error=, fail=)}`` and, under
    ``"failures"``, ``(target, case, detail)`` rows."""
    rng = np.random.default_rng(seed)
    counts = {t: Counter() for t in targets}
    failures = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="octomerge_fuzz_") as tmp:
        folder = Path(tmp) / "case"
        folder.mkdir()
        seeds = seed_files(Path(tmp))
        k = 0
        while True:
            if cases is not None and k >= cases * len(targets):
                break
            if seconds is not None and time.perf_counter() - t0 > seconds:
                break
            target = targets[k % len(targets)]
            k += 1
            source = "pcd_ascii" if target == "pcd" and rng.random() < 0.5 else target
            data = mutate(seeds[source], source, rng)
            outcome, detail = run_case(target, data, folder, cli, timeout)
            counts[target][outcome] += 1
            if outcome == "fail":
                failures.append((target, k, detail))
                if save_failures is not None:
                    save_failures.mkdir(parents=True, exist_ok=True)
                    name = f"{target}_{k}{SUFFIX.get(target, '.' + target)}"
                    (save_failures / name).write_bytes(data)
    return {"counts": counts, "failures": failures, "seconds": time.perf_counter() - t0}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--cases", type=int, default=None, help="cases per target (instead of time)")
    p.add_argument("--targets", nargs="+", default=list(TARGETS), choices=TARGETS)
    p.add_argument("--cli", action="store_true", help="also run info / convert on each map")
    p.add_argument("--case-timeout", type=float, default=20.0)
    p.add_argument("--save-failures", type=Path, default=None)
    args = p.parse_args(argv)
    res = campaign(args.seed, args.cases, None if args.cases else args.seconds,
                   tuple(args.targets), args.cli, args.case_timeout, args.save_failures)
    print(f"fuzz campaign: seed {args.seed}, {res['seconds']:.0f} s, cli={args.cli}")
    print("| target | cases | loaded | loaded lenient | documented error | failure |")
    print("|---|---:|---:|---:|---:|---:|")
    total = Counter()
    for t, c in res["counts"].items():
        n = sum(c.values())
        total.update(c)
        print(f"| {t} | {n} | {c['ok']} | {c['lenient']} | {c['error']} | {c['fail']} |")
    print(f"| all | {sum(total.values())} | {total['ok']} | {total['lenient']} | {total['error']} "
          f"| {total['fail']} |")
    kinds = Counter((t, d.split(':')[0] if ':' in d else d) for t, _, d in res["failures"])
    for (t, kind), n in kinds.most_common():
        example = next(d for tt, _, d in res["failures"] if tt == t and d.startswith(kind))
        print(f"  {t}: {n} x {example}")
    return 1 if total["fail"] else 0


if __name__ == "__main__":
    sys.exit(main())
