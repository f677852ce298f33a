"""How long Ctrl-C takes to end `refflow track`: SIGINT sent while frames are measured, time
until the process has exited.

Each trial starts `refflow track CLIP --mask MASK --mm-per-px 1 --jobs J` on a painted-bar
clip (``../shared/bench/clips``; `occlusion` by default: its sheet frames are measured in
full, the slowest frames there are), waits until the progress bar shows the frame loop at
work (``--after`` frames done), waits ``--delay`` seconds more (trials spread the delay
over one frame's time so that the signal lands at different points of a frame), sends
SIGINT the way a terminal's Ctrl-C does (to the process group) and times the exit. Each
trial also checks what the user is promised: exit status 130, the one-line message, no
output file left. Prints a Markdown table and the median and worst latency.

    .venv/bin/python benchmarks/bench_interrupt.py [--clip occlusion] [--jobs 2] [--trials 6]

Asserts nothing (latencies depend on the machine and its load).
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT.parent / "shared" / "bench" / "clips"
MESSAGE = "interrupted; no output written"


def _frames_done(text: str) -> int:
    """The progress bar's latest count of frames done (tqdm writes ``  12/180 [...``)."""
    done = -1
    for part in text.replace("\r", "\n").splitlines():
        head = part.split("|")[-1].strip().split("/")[0] if "/" in part else ""
        if head.isdigit():
            done = int(head)
    return done


def trial(video: Path, mask: Path, *, jobs: int, after: int, delay: float, folder: Path,
          method: str = "deepflow", timeout: float = 120.0) -> dict:
    """One interrupted run: the latency from SIGINT to exit and what the run left."""
    out = folder / "out.csv"
    err_path = folder / "stderr.txt"
    cmd = [sys.executable, "-m", "flow.cli", "track", str(video), "--mask", str(mask), "--mm-per-px", "1",
           "--method", method, "--jobs", str(jobs), "--out", str(out)]
    with err_path.open("w") as err:
        # A new process group, with SIGINT's default action (a script started in the background
        # inherits SIGINT ignored), so the group gets what a terminal's Ctrl-C sends.
        proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err, start_new_session=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        started = time.monotonic()
        while _frames_done(err_path.read_text()) < after:
            if proc.poll() is not None or time.monotonic() - started > timeout:
                proc.kill()
                last = (err_path.read_text().strip().splitlines() or [""])[-1]
                return {"error": f"the run ended or stalled before frame {after}: rc {proc.poll()}, {last}"}
            time.sleep(0.02)
        time.sleep(delay)
        if proc.poll() is not None:
            return {"error": "the run ended before it was interrupted"}
        sent = time.monotonic()
        os.killpg(proc.pid, signal.SIGINT)
        try:
            rc = proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            return {"error": f"still running {timeout:.0f} s after SIGINT"}
        latency = time.monotonic() - sent
    text = err_path.read_text()
    left = sorted(p.name for p in folder.iterdir() if p.name != "stderr.txt")
    return {"latency_s": latency, "rc": rc, "message": MESSAGE in text, "left": left}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clip", default="occlusion", help="a bench clip's folder name")
    parser.add_argument("--clips-dir", default=str(BENCH), help="where the bench clips are")
    parser.add_argument("--method", default="deepflow")
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--trials", type=int, default=6)
    parser.add_argument("--after", type=int, default=20, help="frames done before the signal")
    parser.add_argument("--spread", type=float, default=1.0, help="delays spread over 0..SPREAD s")
    args = parser.parse_args(argv)
    folder = Path(args.clips_dir) / args.clip
    rows = []
    for k in range(args.trials):
        delay = args.spread * k / max(args.trials - 1, 1)
        with tempfile.TemporaryDirectory() as tmp:
            r = trial(folder / "clip.mp4", folder / "mask.png", jobs=args.jobs, after=args.after,
                      delay=delay, folder=Path(tmp), method=args.method)
        rows.append((delay, r))
        print(f"delay {delay:.2f} s: " + (f"{r['latency_s']:.2f} s, rc {r['rc']}, message {r['message']}, "
                                          f"left {r['left']}" if "error" not in r else r["error"]),
              file=sys.stderr, flush=True)
    print(f"`refflow track` {args.clip} --method {args.method} --jobs {args.jobs}, SIGINT after frame "
          f"{args.after} + delay; load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores\n")
    print("| delay s | exit after SIGINT s | exit status | message | files left |")
    print("|---|---|---|---|---|")
    for delay, r in rows:
        if "error" in r:
            print(f"| {delay:.2f} | {r['error']} ||||")
        else:
            print(f"| {delay:.2f} | {r['latency_s']:.2f} | {r['rc']} | {'yes' if r['message'] else 'no'} | "
                  f"{', '.join(r['left']) or 'none'} |")
    latencies = [r["latency_s"] for _, r in rows if "error" not in r]
    if latencies:
        print(f"\nmedian {statistics.median(latencies):.2f} s, worst {max(latencies):.2f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
