"""Part 7: batches — throughput of the process pool against one-by-one registration, the
engine's overhead per fit, and the manifest's bookkeeping at 10,000 inputs with kills.

1. Throughput, embedded model, 40 scans, `--method statistical --preset paper` (500 iterations,
   ~1–2 s a fit: long enough that the fits dominate, short enough to run 40 four ways): (a) one
   `statfit register` command per scan, as a shell loop would; (b) every scan in one process
   (`register()` in a loop: no engine at all); (c) `statfit batch register --workers 1`; (d) the same
   with `--workers 2`. Whole-command wall seconds, imports and model loading included.
2. The same (b)–(d) on the ICT head with the default pipeline (4 study scans): the engine's
   overhead per ICT-sized fit is (c − b) / b.
3. Bookkeeping: 10,000 tiny inputs with the fit replaced by a stub that copies the input, on 2
   workers: seconds for the whole batch, and for a rerun that skips everything; then 20 fresh
   batches, each killed (SIGKILL) at a random moment of its run, the manifest checked, resumed to
   the end and checked again: every input done once, each recorded output present with its size.
4. A pool's start: seconds until each of its workers has answered a call, in a fresh process, with
   the workers forked from the fork server the local pool uses (imports paid once, in the server)
   against fresh interpreters (spawned, as before session 40), 1, 2 and 4 workers.
"""
from __future__ import annotations

import json
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from common import ROOT, Section, markdown_table

EMBEDDED = {"scans": 40, "method": ["--method", "statistical", "--preset", "paper"]}
QUICK_EMBEDDED = {"scans": 6, "method": ["--method", "statistical", "--preset", "paper", "--iterations", "100"]}
ICT_CASES = ("jaw-open", "smile", "brow-up", "cheek-puff")
BOOKKEEPING_INPUTS, QUICK_BOOKKEEPING_INPUTS = 10_000, 1_000
KILLS, QUICK_KILLS = 20, 3
STATFIT = [sys.executable, "-m", "statfit_cli.main"]
BENCH = str(ROOT / "benchmarks")


def copy_input(job, source: str):
    """The stub fit of the bookkeeping benchmark: the input's bytes as the output."""
    from statfit.batch.fits import Outcome

    return Outcome(Path(source).read_bytes(), {}, None, 0.0)


def bookkeeping_run(inputs: str, out_dir: str, workers: int) -> None:
    """One batch of the stub over ``inputs`` (a glob) into ``out_dir`` (run in a child, to be killed)."""
    from statfit.batch.engines import LocalPool
    from statfit.batch.fits import FitJob
    from statfit.batch.plan import expand_inputs, plan_outputs
    from statfit.batch.run import run_batch
    from statfit.core.methods import resolve

    out = Path(out_dir)
    out.mkdir(exist_ok=True)
    items = plan_outputs(expand_inputs([inputs], exclude=out), out)
    engine = LocalPool(workers)
    try:
        report = run_batch(items, FitJob("register", None, None, resolve("none")), out, engine, work=copy_input)
    finally:
        engine.close()
    print(json.dumps({"done": report.done, "skipped": report.skipped, "failed": len(report.failed)}))


def pool_start(workers: int, how: str) -> None:
    """Print the seconds two new local pools of ``workers`` each take until all their workers have
    answered, one after the other (as when a hung fit's pool is replaced), in a fresh child:
    ``how`` "fork server" (the pool's own way) or "spawn" (a fresh interpreter each)."""
    import multiprocessing

    from statfit.batch import engines

    if how == "spawn":
        engines._worker_context = lambda: multiprocessing.get_context("spawn")
    for _ in range(2):
        started = time.perf_counter()
        engine = engines.LocalPool(workers)
        engine.submit(engines._pid_after, 0.0).result()
        print(time.perf_counter() - started)
        engine.close()


def _pool_starts() -> dict:
    seconds = {}
    for workers in (1, 2, 8):
        for how in ("fork server", "spawn"):   # side by side, each in a fresh process
            code = f"import batch; batch.pool_start({workers}, {how!r})"
            out = subprocess.run(_child(code), check=True, capture_output=True, text=True).stdout
            first, second = map(float, out.split()[-2:])
            seconds[f"{how}, {workers} worker{'s' * (workers > 1)}"] = {"first": first, "replaced": second}
    return seconds


def _timed(command: list[str]) -> float:
    started = time.perf_counter()
    subprocess.run(command, check=False, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - started


def _child(code: str) -> list[str]:
    return [sys.executable, "-c", f"import sys; sys.path.insert(0, {BENCH!r}); {code}"]


def _in_one_process(scans: list[Path], out: Path, model: str | None, method: list[str]) -> list[str]:
    """A child registering every scan in turn in one process, like the CLI would (model opened once)."""
    options = dict(zip(method[::2], method[1::2]))
    kwargs = {"method": options.get("--method", "default"), "preset": options.get("--preset", "tuned")}
    if "--iterations" in options:
        kwargs["iterations"] = int(options["--iterations"])
    code = ("from pathlib import Path; from statfit.model.importers.cache import open_model; "
            "from statfit.io.mesh import read_points, mesh_bytes; from statfit.io.files import write_atomic; "
            "from statfit import register; "
            "from statfit.core.threads import flush_denormals_everywhere; flush_denormals_everywhere(); "
            f"model = open_model({model!r} and Path({model!r})); "
            f"[write_atomic(Path({str(out)!r}) / (Path(s).stem + '.ply'), mesh_bytes(register(model, read_points(s), "
            f"**{kwargs!r}).vertices, model.faces, 'ply')) for s in {[str(s) for s in scans]!r}]")
    return _child(code)


def _throughput(scans: list[Path], model: str | None, method: list[str], shell_loop: bool) -> dict:
    model_option = ["--model", model] if model else []
    seconds = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        if shell_loop:
            started = time.perf_counter()
            for scan in scans:
                subprocess.run([*STATFIT, "register", str(scan), "-o", str(work / f"{scan.stem}.ply"), "-q",
                                *model_option, *method], check=True, stdout=subprocess.DEVNULL)
            seconds["one command per scan"] = time.perf_counter() - started
        (work / "one").mkdir()
        seconds["one process, no engine"] = _timed(_in_one_process(scans, work / "one", model, method))
        for workers in (1, 2):
            seconds[f"batch, {workers} worker{'s' * (workers > 1)}"] = _timed(
                [*STATFIT, "batch", "register", *map(str, scans), "--out-dir", str(work / f"w{workers}"),
                 "--workers", str(workers), "-q", *model_option, *method])
            assert len(list((work / f"w{workers}").rglob("*.ply"))) == len(scans), "a batch fit failed"
    return seconds


def _embedded_scans(folder: Path, count: int) -> list[Path]:
    import numpy as np

    from statfit.io.mesh import points_bytes
    from statfit.model.statmodel import default_model_path, load_model
    from statfit.synth.sample import sample_target, scan_from_view

    model = load_model(default_model_path())
    paths = []
    for index in range(count):
        rng = np.random.default_rng(1000 + index)
        target = sample_target(model, rng)
        path = folder / f"scan{index:03d}.ply"
        path.write_bytes(points_bytes(scan_from_view(target, model.faces, rng, 4300, rng.uniform(-40, 40))))
        paths.append(path)
    return paths


def _ict_scans(folder: Path) -> list[Path]:
    from cases import scan_case
    from statfit.io.mesh import points_bytes

    paths = []
    for name in ICT_CASES:
        path = folder / f"{name}.ply"
        path.write_bytes(points_bytes(scan_case(name).points))
        paths.append(path)
    return paths


def _check_manifest(out: Path) -> dict:
    """Counts from the manifest, asserting what a kill must never break."""
    from statfit.batch.manifest import MANIFEST_NAME

    lines = (out / MANIFEST_NAME).read_bytes().split(b"\n")
    rows, unreadable = [], 0
    for number, line in enumerate(lines):
        if not line:
            continue
        try:
            rows.append(json.loads(line))
        except ValueError:
            unreadable += 1  # only a line cut short by a kill; later lines start afresh
    done = [r for r in rows if r["event"] == "fit" and r["status"] == "done"]
    for row in done:
        output = out / row["output"]
        assert output.is_file() and output.stat().st_size == row["bytes"], f"{output} missing or changed"
    assert not [r for r in rows if r["event"] == "fit" and r["status"] != "done"], "a stub fit failed"
    inputs = [r["input"] for r in done]
    return {"done": len(set(inputs)), "redone": len(inputs) - len(set(inputs)), "cut_lines": unreadable}


def _bookkeeping(count: int, kills: int) -> dict:
    rng = random.Random(0)
    with tempfile.TemporaryDirectory() as tmp:
        inputs = Path(tmp) / "in"
        for shard in range(count // 1000 + 1):
            (inputs / f"{shard:02d}").mkdir(parents=True)
        for index in range(count):
            (inputs / f"{index // 1000:02d}" / f"{index:05d}.ply").write_bytes(b"%d" % index)
        pattern = str(inputs / "**" / "*.ply")
        run = lambda out: _child(f"import batch; batch.bookkeeping_run({pattern!r}, {out!r}, 2)")  # noqa: E731
        first = _timed(run(str(Path(tmp) / "full")))
        rerun = _timed(run(str(Path(tmp) / "full")))
        full = _check_manifest(Path(tmp) / "full")
        rounds = []
        for index in range(kills):  # each round: a fresh batch killed at a random moment, checked, resumed, checked
            out = Path(tmp) / f"killed{index}"
            process = subprocess.Popen(run(str(out)), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            moment = rng.uniform(0.5, first)  # starting up, fitting, writing: anywhere in the run
            time.sleep(moment)
            process.send_signal(signal.SIGKILL)
            process.wait()
            after_kill = _check_manifest(out) if (out / "manifest.jsonl").exists() else {"done": 0, "redone": 0,
                                                                                        "cut_lines": 0}
            subprocess.run(run(str(out)), check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            rounds.append({"moment_s": moment, "after_kill": after_kill, "resumed": _check_manifest(out)})
            shutil.rmtree(out)
    return {"inputs": count, "first_run_s": first, "rerun_s": rerun, "full": full, "rounds": rounds}


def measure(quick: bool) -> dict:
    from common import ICT_MODEL

    embedded = QUICK_EMBEDDED if quick else EMBEDDED
    with tempfile.TemporaryDirectory() as tmp:
        scans = _embedded_scans(Path(tmp), embedded["scans"])
        data = {"embedded": _throughput(scans, None, embedded["method"], shell_loop=True)}
        if ICT_MODEL.is_file():
            ict = _ict_scans(Path(tmp))[: 2 if quick else None]
            data["ict"] = _throughput(ict, str(ICT_MODEL), ["--iterations", "200"] if quick else [], shell_loop=False)
    data["bookkeeping"] = _bookkeeping(QUICK_BOOKKEEPING_INPUTS if quick else BOOKKEEPING_INPUTS,
                                       QUICK_KILLS if quick else KILLS)
    data["pool_start"] = _pool_starts()
    return data


def _speed_table(seconds: dict, count: int) -> str:
    base = seconds["one process, no engine"]
    return markdown_table(["how", "wall s", "s per scan", "speed-up vs one process"],
                          [[how, s, s / count, base / s] for how, s in seconds.items()])


def run(quick: bool, device: str, image_dir) -> Section:
    return section(measure(quick), quick)


def section(data: dict, quick: bool) -> Section:
    """The report's section for measured ``data``."""
    embedded = QUICK_EMBEDDED if quick else EMBEDDED
    parts = [f"**Embedded model**, {embedded['scans']} scans (4,300 points), `{' '.join(embedded['method'])}`, "
             f"whole-command wall seconds:\n\n{_speed_table(data['embedded'], embedded['scans'])}"]
    if "ict" in data:
        ict = data["ict"]
        overhead = (ict["batch, 1 worker"] - ict["one process, no engine"]) / ict["one process, no engine"]
        count = 2 if quick else len(ICT_CASES)
        parts.append(f"**ICT head**, {count} study scans, the default pipeline:\n\n{_speed_table(ict, count)}\n\n"
                     f"Engine overhead per ICT-sized fit (batch with 1 worker vs one process): {100 * overhead:+.1f}%.")
    book = data["bookkeeping"]
    rounds = book["rounds"]
    complete = sum(r["resumed"]["done"] == book["inputs"] for r in rounds)
    parts.append(
        f"**Bookkeeping**: {book['inputs']:,} tiny inputs, the fit replaced by a stub copying its input, 2 workers: "
        f"{book['first_run_s']:.1f} s for the batch (imports and worker start included), {book['rerun_s']:.1f} s "
        f"for a rerun that skips every input. Then {len(rounds)} fresh batches, each killed (SIGKILL) at a random "
        f"moment ({min(r['moment_s'] for r in rounds):.1f}–{max(r['moment_s'] for r in rounds):.1f} s), checked, "
        f"resumed and checked again: after every kill each recorded output was present with its recorded size; "
        f"inputs recorded when killed: {', '.join(str(r['after_kill']['done']) for r in rounds)}; lines cut short "
        f"by a kill: {sum(r['after_kill']['cut_lines'] for r in rounds)}; inputs fitted twice across kill and "
        f"resume: {sum(r['resumed']['redone'] for r in rounds)} (only an output written but not yet recorded when "
        f"the kill came is redone); resumed batches that finished all {book['inputs']:,}: {complete} of "
        f"{len(rounds)}.")
    if "pool_start" in data:
        parts.append("**A pool's start** (seconds until every worker has answered, in a fresh process; then a "
                     "second pool's, as when a hung fit's pool is replaced; the fork server's start included "
                     "in the first):\n\n" + markdown_table(
                         ["workers started", "first pool s", "replaced pool s"],
                         [[how, s["first"], s["replaced"]] for how, s in data["pool_start"].items()]))
    return Section("batch", "Batches: throughput, engine overhead, bookkeeping", "\n\n".join(parts), data=data)
