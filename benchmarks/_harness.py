"""What the benchmark suites share: the machine, timing, modes, and their blocks of RESULTS.md."""

from __future__ import annotations

import argparse
import json
import math
import os
import pathlib
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = pathlib.Path(__file__).resolve().parent
RESULTS = HERE / "RESULTS.md"


# --- the machine ---------------------------------------------------------------------------


def cpu() -> dict:
    """Processor name, cores, clock (GHz) and SIMD flags (from /proc/cpuinfo where it exists)."""
    name, mhz, flags = platform.processor() or platform.machine(), 0.0, set()
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = (s.strip() for s in line.partition(":"))
            if key == "model name":
                name = value
            elif key == "cpu MHz" and not mhz:
                mhz = float(value)
            elif key == "flags" and not flags:
                flags = set(value.split())
    except OSError:
        pass
    return dict(name=name, cores=os.cpu_count() or 1, ghz=mhz / 1e3, flags=flags)


def machine_line() -> str:
    """One line: processor, versions, JAX devices."""
    import diffrax
    import equinox
    import jax
    import scipy

    c, devices = cpu(), jax.devices()
    name = " ".join(re.sub(r"\((R|TM)\)|\bCPU\b|\bProcessor\b", "", c["name"]).split())
    n = len(devices)
    return (
        f"{name}, {c['cores']} cores @ {c['ghz']:.2f} GHz; python {platform.python_version()}, "
        f"jax {jax.__version__}, diffrax {diffrax.__version__}, equinox {equinox.__version__}, "
        f"numpy {np.__version__}, scipy {scipy.__version__}; {n} {devices[0].platform} "
        f"device{'s' if n > 1 else ''}"
    )


# --- timing ----------------------------------------------------------------------------------


class Timing:
    """Wall-clock and process CPU time of a first (compiling) call and of later calls."""

    def __init__(self):
        self.first_wall = self.first_cpu = math.nan
        self.walls: list[float] = []
        self.cpus: list[float] = []

    @property
    def wall(self) -> float:
        return statistics.median(self.walls) if self.walls else self.first_wall

    @property
    def cpu(self) -> float:
        return statistics.median(self.cpus) if self.cpus else self.first_cpu

    @property
    def compile(self) -> float:
        """The first call less the median of the later ones: compilation (wall clock)."""
        return self.first_wall - self.wall


def call(fn):
    """(wall s, CPU s, output) of `fn()`, waiting for its arrays (`jax.block_until_ready`)."""
    import jax

    wall, cpu_ = time.perf_counter(), time.process_time()
    out = jax.block_until_ready(fn())
    return time.perf_counter() - wall, time.process_time() - cpu_, out


def interleaved(fns: dict, rounds: int) -> dict:
    """{name: (Timing, output)} of zero-argument callables: a first call each, then `rounds`
    rounds calling each once, so that a shared machine's load falls on all of them alike."""
    timings, outs = {name: Timing() for name in fns}, {}
    for name, fn in fns.items():
        t = timings[name]
        t.first_wall, t.first_cpu, outs[name] = call(fn)
    for _ in range(rounds):
        for name, fn in fns.items():
            wall, cpu_, outs[name] = call(fn)
            timings[name].walls.append(wall)
            timings[name].cpus.append(cpu_)
    return {name: (timings[name], outs[name]) for name in fns}


def paired(a: Timing, b: Timing, what: str = "walls") -> tuple[float, float, float]:
    """Median and quartiles of the round-by-round ratios a / b of two interleaved runs."""
    r = np.asarray(getattr(a, what)) / np.asarray(getattr(b, what))
    if not r.size:
        r = np.asarray([a.first_wall / b.first_wall])
    return float(np.median(r)), float(np.quantile(r, 0.25)), float(np.quantile(r, 0.75))


def rounds(args, default: int) -> int:
    """Interleaved rounds: 1 in a smoke run, else `--rounds` or the mode's default."""
    return 1 if getattr(args, "smoke", False) else (args.rounds or default)


def interp_loglog(x, xs, ys) -> float:
    """y at x, linear in log-log through the points (xs, ys); beyond them from the nearest two."""
    xs, ys = np.asarray(xs, float), np.asarray(ys, float)
    keep = np.isfinite(xs) & np.isfinite(ys) & (xs > 0) & (ys > 0)
    lx, ly = np.log(xs[keep]), np.log(ys[keep])
    order = np.argsort(lx)
    lx, ly = lx[order], ly[order]
    i = int(np.clip(np.searchsorted(lx, math.log(x)) - 1, 0, len(lx) - 2))
    slope = (ly[i + 1] - ly[i]) / (lx[i + 1] - lx[i])
    return math.exp(ly[i] + slope * (math.log(x) - lx[i]))


def fresh_process(code: str, *args: str, env: dict | None = None) -> dict:
    """Run `code` in a new Python process; its last line of output, read as JSON."""
    full_env = dict(os.environ, **(env or {}))
    full_env["PYTHONPATH"] = os.pathsep.join(
        p for p in (str(HERE), str(HERE.parent), full_env.get("PYTHONPATH", "")) if p
    )
    out = subprocess.run(
        [sys.executable, "-c", code, *args], env=full_env, capture_output=True, text=True
    )
    if out.returncode:
        raise RuntimeError(out.stderr[-3000:])
    return json.loads(out.stdout.strip().splitlines()[-1])


# --- tables, charts, RESULTS.md ----------------------------------------------------------------


def table(headers, rows) -> str:
    """A markdown table; `headers` and each row a list of cells or one string "a | b | c"
    (no spaces around the cells' bars in the table written)."""

    def line(cells):  # cells split at unescaped bars
        cells = re.split(r"(?<!\\)\|", cells) if isinstance(cells, str) else cells
        return "|" + "|".join(str(x).strip() for x in cells) + "|"

    n = len(headers.split(" | ")) if isinstance(headers, str) else len(headers)
    return "\n".join([line(headers), "|" + "---|" * n, *map(line, rows)])


def verdict(met: bool) -> str:
    return "**met**" if met else "**missed**"


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure_path(name: str, args) -> pathlib.Path:
    """Where a chart goes: beside RESULTS.md, or a temporary folder in a smoke run."""
    if getattr(args, "smoke", False):
        return pathlib.Path(tempfile.gettempdir()) / f"smoke-{name}"
    return HERE / name


def command(args) -> str:
    """The command as the file's head reads it: `python benchmarks/<command>`."""
    return " ".join([pathlib.Path(sys.argv[0]).name, *sys.argv[1:]])


def write(key: str, title: str, body: str, args, header: str | None = None) -> None:
    """Print a block and put it in RESULTS.md between `<!-- key -->` and `<!-- /key -->`, under
    its suite's `## ` heading, after the command and the machine (not in a smoke run): by the
    name the file's list of machines gives it (`- machine B: ...`), else in full."""
    text = RESULTS.read_text() if RESULTS.exists() else "# Benchmark results\n"
    if header is None:  # a machine the file's list names goes by its name
        line = machine_line()
        named = re.search(rf"^- (machine \w+): {re.escape(line)}$", text, flags=re.M)
        header = f"`{command(args)}` ({named[1] if named else line})"
    block = f"<!-- {key} -->\n### {title}\n\n{header}\n\n{body.strip()}\n<!-- /{key} -->"
    print(block, flush=True)
    if getattr(args, "smoke", False):
        return
    pattern = rf"<!-- {re.escape(key)} -->.*?<!-- /{re.escape(key)} -->"
    if re.search(pattern, text, flags=re.S):
        text = re.sub(pattern, lambda _: block, text, flags=re.S)
    else:
        suite = key.split()[0]
        heading = re.search(rf"^## {re.escape(suite)}\b.*$", text, flags=re.M)
        if heading is None:
            text = text.rstrip("\n") + f"\n\n## {suite}\n\n{block}\n"
        else:
            nxt = re.search(r"^## ", text[heading.end() :], flags=re.M)
            at = heading.end() + nxt.start() if nxt else len(text)
            text = text[:at].rstrip("\n") + f"\n\n{block}\n\n" + text[at:]
    RESULTS.write_text(text)


# --- modes -------------------------------------------------------------------------------------


def parse(doc: str, modes: dict, options=None):
    """The suite's arguments: one flag per mode (none: every mode), `--smoke` (tiny sizes, every
    code path, nothing written), and the suite's own `options(parser)`."""
    p = argparse.ArgumentParser(
        description=doc.splitlines()[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="\n".join(f"  --{m}: {what}" for m, (_, what) in modes.items()),
    )
    for m in modes:
        p.add_argument(f"--{m}", action="store_true")
    p.add_argument("--smoke", action="store_true", help="tiny sizes, every path, writes nothing")
    p.add_argument("--rounds", type=int, default=None, help="interleaved timing rounds")
    if options:
        options(p)
    args = p.parse_args()
    args.modes = [m for m in modes if getattr(args, m.replace("-", "_"))] or list(modes)
    return args


def run(modes: dict, args) -> None:
    """Run one mode here; several, each in its own process (a mode may ask for its own devices)."""
    if len(args.modes) == 1:
        modes[args.modes[0]][0](args)
        return
    flags = [a for a in sys.argv[1:] if a.lstrip("-") not in modes]
    for m in args.modes:
        print(f"== {pathlib.Path(sys.argv[0]).name} --{m}", flush=True)
        subprocess.run([sys.executable, sys.argv[0], f"--{m}", *flags], check=True)
