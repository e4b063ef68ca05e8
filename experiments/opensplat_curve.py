#!/usr/bin/env python3
"""OpenSplat (the outside CPU 3DGS trainer) on the objects' input views with their true cameras: held-out PSNR after
5, 10, 30 and 120 s, beside `scripts/paper_tables posed-refine` (experiments/README.md).

  experiments/opensplat_curve.py [--views 9,26,3,20] [--points 5120] [--seconds 120] OBJECT_DIR...

Needs build/experiments/opensplat_inputs and an OpenSplat binary ($OPENSPLAT, default /tmp/opensplat/build/opensplat),
built on Debian 12 with:
  apt-get install libtorch-dev libopencv-dev nlohmann-json3-dev libnanoflann-dev libcxxopts-dev
  git clone https://github.com/pierotofy/OpenSplat /tmp/opensplat   # commit 15b7e80
  cmake -S /tmp/opensplat -B /tmp/opensplat/build -G Ninja -DCMAKE_BUILD_TYPE=Release -DGPU_RUNTIME=CPU \\
        -DFETCHCONTENT_TRY_FIND_PACKAGE_MODE=ALWAYS \\
        -DCMAKE_PREFIX_PATH="/usr/lib/x86_64-linux-gnu/cmake/Torch;/usr/share/nanoflann/cmake"
  ninja -C /tmp/opensplat/build opensplat
OpenSplat runs with its defaults (--cpu --keep-crs), started from the point cloud eval's posed fit starts from
(random_gaussians_in_views: --points in the silhouettes' hull); the clock starts with its process.
"""
import argparse
import os
import re
import subprocess
import sys
import tempfile
import time

ap = argparse.ArgumentParser()
ap.add_argument("objects", nargs="+")
ap.add_argument("--views", default="9,26,3,20")
ap.add_argument("--points", type=int, default=5120)
ap.add_argument("--seconds", type=float, default=120)
ap.add_argument("--budgets", default="5,10,30,120")
ap.add_argument("--save-every", type=int, default=25)
a = ap.parse_args()
root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
inputs = os.path.join(root, "build", "experiments", "opensplat_inputs")
opensplat = os.environ.get("OPENSPLAT", "/tmp/opensplat/build/opensplat")
budgets = [float(b) for b in a.budgets.split(",")]
rows = []
for obj in a.objects:
    name = os.path.basename(os.path.normpath(obj))
    work = tempfile.mkdtemp(prefix="opensplat_" + name + "_")
    subprocess.run([inputs, obj, "--views", a.views, "--points", str(a.points), "--out", work], check=True,
                   stdout=subprocess.DEVNULL)
    out = os.path.join(work, "splat.ply")
    t0 = time.monotonic()
    p = subprocess.Popen([opensplat, work, "--cpu", "--keep-crs", "-n", "1000000", "-s", str(a.save_every),
                          "-o", out], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    saved = []  # (seconds, step, path)
    for line in p.stdout:
        m = re.match(r"Wrote (.*_(\d+)\.ply)", line.strip())
        if m:
            saved.append((time.monotonic() - t0, int(m.group(2)), m.group(1)))
        if time.monotonic() - t0 > a.seconds:
            p.kill()
            break
    p.wait()
    scores = []
    for b in budgets:
        within = [s for s in saved if s[0] <= b]
        if not within:
            scores.append((b, None, 0))
            continue
        sec, step, path = within[-1]
        r = subprocess.run([inputs, obj, "--views", a.views, "--score", path], check=True, capture_output=True,
                           text=True).stdout
        psnr = float(re.search(r"PSNR ([-\d.]+) dB", r).group(1))
        scores.append((b, psnr, step))
    rows.append((name, scores))
    print(name, " ".join(f"{b:g}s: {'-' if s is None else f'{s:.2f}'} ({n} steps)" for b, s, n in scores), flush=True)
    subprocess.run(["rm", "-rf", work])
print("mean", " ".join(
    f"{b:g}s: {sum(r[1][i][1] for r in rows if r[1][i][1] is not None) / max(1, sum(r[1][i][1] is not None for r in rows)):.2f}"
    for i, b in enumerate(budgets)))
