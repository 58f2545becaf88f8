"""The hostile-file corpus (tests/hostile_files.py): every file is refused in one line on stderr
with exit 2, nothing is written, no input changes, no pickle runs; bombs are refused from their
headers, with memory to spare."""
from __future__ import annotations

import hashlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli
from hostile_files import write_corpus
from statfit.io.image import write_image


@pytest.fixture(scope="module")
def corpus(tmp_path_factory) -> tuple[Path, dict[str, list[str]]]:
    good = tmp_path_factory.mktemp("good")
    assert run_cli(["synth", "scan", "--out", str(good / "scan.ply"), "--gt", str(good / "gt.ply")])[0] == 0
    assert run_cli(["synth", "normals", "--size", "48", "--out", str(good / "n.exr"),
                "--camera-out", str(good / "cam.json")])[0] == 0
    write_image(good / "img.png", np.random.default_rng(0).random((24, 24, 3)).astype(np.float32))
    mask = np.ones((24, 24, 1), np.float32)
    mask[6:12, 6:12] = 0
    write_image(good / "mask.png", mask)
    folder = tmp_path_factory.mktemp("hostile")
    runs = write_corpus(folder, {"scan": good / "scan.ply", "gt": good / "gt.ply", "normals": good / "n.exr",
                                 "camera": good / "cam.json", "image": good / "img.png", "mask": good / "mask.png"})
    return folder, runs


def digest(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.iterdir() if p.is_file()}


def test_the_corpus_is_large(corpus):
    assert len(corpus[1]) >= 60


def test_every_hostile_file_is_refused_in_one_line(corpus, tmp_path):
    folder, runs = corpus
    before = digest(folder)
    failures = []
    for name, argv in runs.items():
        out = tmp_path / name
        out.mkdir()
        code, err = run_cli([a.replace("OUT", str(out)) for a in argv])
        if code != 2 or err.count("\n") != 1 or not err.startswith("statfit: error:") or any(out.iterdir()):
            failures.append(f"{name}: exit {code}, {err.strip()[-300:]!r}, wrote {[p.name for p in out.iterdir()]}")
    assert not failures, "\n".join(failures)
    assert digest(folder) == before
    assert not (folder / "PWNED").exists()


@pytest.mark.parametrize("name", ["image-bomb-20000x20000.png", "model-claims-3e12-values.npz",
                                  "normals-window-100000x100000.exr", "scan-declares-a-trillion.ply"])
def test_bombs_are_refused_without_using_memory(corpus, name, tmp_path):
    """A fresh process reading the bomb peaks below 1 GB (statfit and torch alone take ~0.4)."""
    folder, runs = corpus
    argv = [a.replace("OUT", str(tmp_path)) for a in runs[name]]
    code = ("import sys, atexit; from pathlib import Path\n"
            "def peak():\n"
            "    line = [l for l in Path('/proc/self/status').read_text().splitlines() if l.startswith('VmHWM')]\n"
            "    sys.stderr.write(f'\\npeak_kb {line[0].split()[1]}\\n')\n"
            "atexit.register(peak)\n"
            "from statfit_cli.main import main; main(sys.argv[1:])")
    done = subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-2000:]
    assert int(done.stderr.strip().splitlines()[-1].split()[1]) < 1_000_000
