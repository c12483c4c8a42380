"""
The C export (issue 22): cost per step, stack, flash and agreement with Python, per family.

For each family (the paper's NARX network: bags/model.json; the envelope family: the control
bench's identified model, reports/control-models/default-seed0, identified when missing as
bench_control.py does; ARX(4, 4): least squares on that model's protocol record) the model is
exported with `piezo-narx export` and compiled with gcc -std=c99 -O2, then:

  step       C pnr_step per sample: median over --repeats runs of a 10 s multisine, each timed
             in chunks of 1000 samples (a chunk preempted by the shared machine is an outlier
             the median drops), and the Python Stepper.step the same way, side by side;
  inverse    C pnr_inverse_step per sample over the control bench's references (bench_control
             TASKS, seed 0, whole, slew 1e5 V/s; chunks of 1000 samples, median) and the Python
             PositionController.on_reference in `inverse` mode on the same; single C calls
             timed one by one (median, 99th percentile, largest; most model evaluations);
  agreement  max |C - Python| of the free run on the envelope battery (bench_envelope.BATTERY,
             11 signals x 10 s from rest) and of the inverse's commands on those references;
  stack      worst call chain of pnr_step and pnr_inverse_step, bytes (gcc -fstack-usage
             -fcallgraph-info=su; libm's exp not included);
  flash      size of pnr_model.o: code (.text) and constants (.rodata) in bytes.

Targets (issue 22): C step <= 0.5 us (envelope family), <= 0.2 us (paper network); free run
within 1e-12 m; inverse within 1e-9 V. Timing on a shared machine is noisy: the load average is
printed, C and Python are measured in the same run.

Run: python bench/bench_export.py [--repeats 51] [--narx M] [--envelope M] [--json out.json]
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import statistics
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from bench_control import SLEW, TASKS, identify, reference
from bench_envelope import BATTERY, TEST_SECONDS
from headline import headline
from piezo_narx_ros.control.controller import PositionController
from piezo_narx_ros.export.writer import write_c
from piezo_narx_ros.ident.arx.model import ARXModel
from piezo_narx_ros.ident.model_io import load_model
from piezo_narx_ros.npzfile import read_npz
from piezo_narx_ros.plant import generate

REPO = Path(__file__).resolve().parents[1]
FS = 2000.0
CFLAGS = ['-std=c99', '-O2']

TIMER = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include "pnr_model.h"

#define MAXN 600000
#define CHUNK 1000
static double in_[MAXN], dur_[MAXN];

static int cmp(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static double now(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + 1e-9 * (double)t.tv_nsec;
}

/* argv: step|inverse|free|invrun REPEATS [N]; stdin: the signal (doubles). */
int main(int argc, char **argv)
{
    long n = (long)fread(in_, sizeof(double), MAXN, stdin), k, r, reps = atol(argv[2]);
    long len = argc > 3 ? atol(argv[3]) : n;
    int evals = 0;
    pnr_state_t s;
    pnr_inverse_params_t p;
    pnr_inverse_t inv;
    double y[PNR_N_OUTPUTS], u[PNR_N_INPUTS], t0, t1, t2, acc = 0.0;
    if (!strcmp(argv[1], "free") || !strcmp(argv[1], "invrun")) {
        pnr_inverse_default_params(&p);
        p.slew_rate = atof(argv[4]);
        pnr_inverse_init(&inv, &p);
        for (k = 0; k < n; ++k) {
            if (k % len == 0) {
                pnr_init(&s);
                pnr_inverse_reset(&inv);
            }
            if (argv[1][0] == 'f') {
                pnr_step(&s, &in_[k], y);
            } else {
                pnr_inverse_step(&inv, &in_[k], y);
            }
            fwrite(y, sizeof(double), 1, stdout);
        }
        return 0;
    }
    if (!strcmp(argv[1], "inverse")) {
        pnr_inverse_default_params(&p);
        p.slew_rate = atof(argv[4]);
        if (pnr_inverse_init(&inv, &p)) {
            return 5;
        }
    }
    /* reps timed runs, then (inverse) one more timing every call for the worst one */
    for (r = 0; r <= reps; ++r) {
        int per_call = r == reps;
        if (per_call && argv[1][0] == 's') {
            break;
        }
        pnr_init(&s);
        if (argv[1][0] == 'i') {
            pnr_inverse_reset(&inv);
        }
        t0 = now();
        for (k = 0; k < n; ++k) {
            if (argv[1][0] == 's') {      /* timed in chunks of CHUNK samples */
                pnr_step(&s, &in_[k], y);
                acc += y[0];
                if ((k + 1) % CHUNK == 0) {
                    t1 = now();
                    printf("%.6f\n", 1e9 * (t1 - t0) / CHUNK);
                    t0 = t1;
                }
                continue;
            }
            if (k % len == 0) {
                pnr_inverse_reset(&inv);
            }
            if (per_call) {
                t1 = now();
                pnr_inverse_step(&inv, &in_[k], u);
                t2 = now();
                dur_[k] = t2 - t1;
                evals = inv.evaluations > evals ? inv.evaluations : evals;
            } else {
                pnr_inverse_step(&inv, &in_[k], u);
                if ((k + 1) % CHUNK == 0) {
                    t1 = now();
                    printf("%.6f\n", 1e9 * (t1 - t0) / CHUNK);
                    t0 = t1;
                }
            }
            acc += u[0];
        }
    }
    if (argv[1][0] == 'i') {      /* single calls: median, 99th percentile, largest */
        qsort(dur_, (size_t)n, sizeof(double), cmp);
        printf("calls %.3f %.3f %.3f %d\n", 1e9 * dur_[n / 2],
               1e9 * dur_[(long)(0.99 * (n - 1))], 1e9 * dur_[n - 1], evals);
    }
    fprintf(stderr, "%g\n", acc);
    return 0;
}
"""


def compile_timer(directory: Path) -> Path:
    """Compile the timing program against DIR/pnr_model.c (gcc -std=c99 -O2)."""
    (directory / 'timer.c').write_text(TIMER)
    exe = directory / 'timer'
    subprocess.run(['gcc', *CFLAGS, '-I', str(directory), str(directory / 'timer.c'),
                    str(directory / 'pnr_model.c'), '-lm', '-o', str(exe)], check=True)
    return exe


def c_run(exe, args, data) -> str:
    """Run the timing program on the doubles `data`; returns its stdout (bytes for 'free')."""
    out = subprocess.run([str(exe), *map(str, args)], input=np.ascontiguousarray(
        data, dtype=np.float64).tobytes(), capture_output=True, check=True)
    return out.stdout


def c_times(exe, mode, repeats, data, *extra) -> tuple[list, list]:
    """
    Return per-sample ns of each run and, for the inverse, single calls' figures.

    [median ns, p99 ns, max ns, most model evaluations in one call].
    """
    lines = c_run(exe, [mode, repeats, *extra], data).decode().split('\n')
    calls = [ln for ln in lines if ln.startswith('calls')]
    return ([float(ln) for ln in lines if ln and not ln.startswith('calls')],
            [float(x) for x in calls[0].split()[1:]] if calls else [])


def stack_and_flash(directory: Path) -> dict:
    """Return the worst stack chain of the entry points (bytes) and the object's sizes."""
    obj = directory / 'pnr_model.o'
    subprocess.run(['gcc', *CFLAGS, '-fstack-usage', '-fcallgraph-info=su', '-c',
                    str(directory / 'pnr_model.c'), '-o', str(obj)], check=True,
                   cwd=directory)
    ci = (directory / 'pnr_model.ci').read_text()
    own = {m.group(1): int(m.group(2)) for m in re.finditer(
        r'node: \{ title: "([^"]+)" label: "[^"]*\\n(\d+) bytes', ci)}
    calls = {}
    for m in re.finditer(r'edge: \{ sourcename: "([^"]+)" targetname: "([^"]+)"', ci):
        calls.setdefault(m.group(1), set()).add(m.group(2))

    def worst(fn):
        return own.get(fn, 0) + max((worst(c) for c in calls.get(fn, ())), default=0)

    sizes = {}
    for line in subprocess.run(['size', '-A', str(obj)], capture_output=True, text=True,
                               check=True).stdout.splitlines():
        parts = line.split()
        if len(parts) >= 2 and parts[0] in ('.text', '.rodata', '.data', '.bss'):
            sizes[parts[0]] = int(parts[1])
    return {'stack_step': worst('pnr_step'), 'stack_inverse': worst('pnr_inverse_step'),
            'text': sizes.get('.text', 0), 'rodata': sizes.get('.rodata', 0),
            'data': sizes.get('.data', 0) + sizes.get('.bss', 0)}


def python_step_ns(model, u, repeats, chunk=1000) -> list:
    """Return the Python Stepper's per-sample ns of each chunk of `chunk` samples, every run."""
    out = []
    for _ in range(repeats):
        step = model.stepper().step
        for lo in range(0, u.size - chunk + 1, chunk):
            part = u[lo:lo + chunk]
            t0 = time.perf_counter()
            for x in part:
                step(x)
            out.append(1e9 * (time.perf_counter() - t0) / chunk)
    return out


def python_inverse(model, ref, chunk=1000):
    """
    Run PositionController (inverse mode) over ref.

    Returns the commands (V) and the ns per sample of each chunk of `chunk` samples.
    """
    ctl = PositionController(model, mode='inverse', slew_rate=SLEW)
    period = int(1e9 / FS)
    u = np.empty(ref.size)
    times = []
    t0 = time.perf_counter()
    for k, r in enumerate(ref):
        (_, u[k]), = ctl.on_reference(k * period, r)
        if (k + 1) % chunk == 0:
            t1 = time.perf_counter()
            times.append(1e9 * (t1 - t0) / chunk)
            t0 = t1
    return u, times


def envelope_battery() -> list:
    """Return the envelope battery's inputs (seed 0's signals), V."""
    out = []
    for kind, amp, opt in BATTERY.values():
        opt = dict(opt)
        seed = 7919 if opt.pop('seeded', False) else 0
        out.append(generate(kind, FS, TEST_SECONDS, amp, seed=seed, **opt))
    return out


def bench_family(name, model, repeats, work: Path) -> dict:
    """Every figure of one family."""
    directory = work / name
    write_c(model, directory, source=name)
    exe = compile_timer(directory)
    res = {'kind': model.kind, 'n_params': model.n_params}
    u = generate('multisine', FS, 10.0, 100.0, seed=1)
    c_ns, _ = c_times(exe, 'step', repeats, u)
    py_ns = python_step_ns(model, u, max(2, repeats // 10))
    res['c_step_ns'], res['py_step_ns'] = statistics.median(c_ns), statistics.median(py_ns)
    signals = envelope_battery()
    y_c = np.frombuffer(c_run(exe, ['free', 1, signals[0].size, SLEW],
                              np.concatenate(signals)))
    y_py = np.concatenate([model.simulate(s) for s in signals])
    res['free_run_max_err_m'] = float(np.max(np.abs(y_c - y_py)))
    refs = [reference(task, 0)[0] for task in TASKS]
    err, py_ns, c_ns = 0.0, [], []
    for ref in refs:       # each from rest; chunk medians over every reference
        u_c = np.frombuffer(c_run(exe, ['invrun', 1, ref.size, SLEW], ref))
        u_py, times = python_inverse(model, ref)
        py_ns += times
        err = max(err, float(np.max(np.abs(u_c - u_py))))
        c_ns += c_times(exe, 'inverse', max(3, repeats // 10), ref, ref.size, SLEW)[0]
    res['inverse_max_err_V'] = err
    res['c_inverse_ns'], res['py_inverse_ns'] = statistics.median(c_ns), statistics.median(py_ns)
    all_refs = np.concatenate(refs)
    _, res['c_inverse_calls'] = c_times(exe, 'inverse', 0, all_refs, all_refs.size, SLEW)
    res.update(stack_and_flash(directory))
    return res


def models(args):
    """Return {name: model} of the families benchmarked."""
    env_path = args.envelope or identify('default', args.models / 'default-seed0', 0)
    out = {'narx (paper)': load_model(args.narx), 'hysteresis_narx (envelope)':
           load_model(env_path)}
    rec = read_npz(Path(env_path).parent / 'protocol.npz', ('u', 'y'), error=RuntimeError) \
        if (Path(env_path).parent / 'protocol.npz').is_file() else None
    if rec is not None:
        arx = ARXModel(4, 4).fit(rec['u'], rec['y'], fs=FS)
        arx.output_range = out['hysteresis_narx (envelope)'].output_range
        out['arx (4, 4)'] = arx
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n\n')[0])
    ap.add_argument('--repeats', type=int, default=51, help='timed runs of the C step')
    ap.add_argument('--narx', type=Path, default=REPO / 'bags' / 'model.json')
    ap.add_argument('--envelope', type=Path, help='an envelope-family model (default: the '
                    "control bench's seed-0 model, identified when missing)")
    ap.add_argument('--models', type=Path, default=REPO / 'reports' / 'control-models')
    ap.add_argument('--json', type=Path, help='write every figure here')
    args = ap.parse_args()
    if shutil.which('gcc') is None:
        raise SystemExit('gcc is needed')
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, model in models(args).items():
            print(f'{name}: exporting, compiling, timing ...', flush=True)
            results[name] = bench_family(name, model, args.repeats, Path(tmp))
    load = os.getloadavg()
    gcc = subprocess.run(['gcc', '-dumpfullversion'], capture_output=True, text=True).stdout
    print(f'\ngcc {gcc.strip()} {" ".join(CFLAGS)}; load average {load[0]:.2f} {load[1]:.2f} '
          f'{load[2]:.2f} on {os.cpu_count()} cores')
    print(f'{"free run":28s} {"params":>6s} {"C step":>9s} {"Py step":>9s} {"Py/C":>6s} '
          f'{"stack B":>7s} {"text B":>7s} {"rodata B":>8s} {"max|C-Py| m":>11s}')
    for name, r in results.items():
        print(f'{name:28s} {r["n_params"]:6d} {r["c_step_ns"] / 1e3:7.3f}us '
              f'{r["py_step_ns"] / 1e3:7.3f}us {r["py_step_ns"] / r["c_step_ns"]:6.1f} '
              f'{r["stack_step"]:7d} {r["text"]:7d} {r["rodata"]:8d} '
              f'{r["free_run_max_err_m"]:11.1e}')
        headline(f'C export {name}: pnr_step per sample (Python Stepper.step); max |C - Python| '
                 'free run', f'{r["c_step_ns"] / 1e3:.3f} µs ({r["py_step_ns"] / 1e3:.3f} µs); '
                 f'{r["free_run_max_err_m"]:.1e} m', '<= 1e-12 m', 'export.md')
    print(f'\n{"inverse":28s} {"C/sample":>9s} {"call p50":>9s} {"call p99":>9s} '
          f'{"call max":>9s} {"Py/sample":>9s} {"Py/C":>6s} {"evals":>5s} {"stack B":>7s} '
          f'{"max|C-Py| V":>11s}')
    for name, r in results.items():
        p50, p99, top, evals = r['c_inverse_calls']
        print(f'{name:28s} {r["c_inverse_ns"] / 1e3:7.3f}us {p50 / 1e3:7.3f}us '
              f'{p99 / 1e3:7.3f}us {top / 1e3:7.1f}us {r["py_inverse_ns"] / 1e3:7.1f}us '
              f'{r["py_inverse_ns"] / r["c_inverse_ns"]:6.0f} {evals:5.0f} '
              f'{r["stack_inverse"]:7d} {r["inverse_max_err_V"]:11.1e}')
    print('C step / Py step: pnr_step / Stepper.step per sample, median over runs of a 10 s '
          'multisine; inverse: pnr_inverse_step / PositionController.on_reference (inverse mode) '
          'over the control bench references, single C calls timed separately (evals: most '
          'model evaluations in one call; the largest call time is mostly preemption on a '
          'shared machine); stack: worst call chain without libm; '
          'text / rodata: pnr_model.o; max|C-Py|: free run on the envelope battery, commands '
          'on the control references.')
    if args.json:
        args.json.write_text(json.dumps({'load': load, 'gcc': gcc.strip(), 'cflags': CFLAGS,
                                         'results': results}, indent=1))


if __name__ == '__main__':
    main()
