"""Reads the frame logs bench/desktop-converge/run.sh wrote (the folder is the argument): per run,
the first volume frame and the last new one (converged when none came in the last 5 s), and
seconds per volume frame while orbiting."""
import csv
import glob
import sys

folder = sys.argv[1]


def rows(path):
    with open(path) as f:
        return [(float(r["seconds"]), int(r["volume_frames"])) for r in csv.DictReader(f)]


for kind in ("still", "orbit"):
    for b in ("before", "after"):
        for path in sorted(glob.glob(f"{folder}/{kind}-{b}-*.csv")):
            rs = rows(path)
            name = path.split("/")[-1]
            end = rs[-1][0]
            first = next((t for t, f in rs if f > 0), None)
            if first is None:
                print(f"{name}: no volume frame")
                continue
            last_change, prev = None, 0
            for t, f in rs:
                if f != prev:
                    last_change, prev = t, f
            if kind == "still":
                settled = end - last_change > 5
                print(f"{name}: first volume frame {first:.1f} s, last new frame {last_change:.1f} s "
                      f"({'converged' if settled else 'NOT settled'} by {end:.0f} s), {rs[-1][1]} volume frames")
            else:
                after = [(t, f) for t, f in rs if t >= first]
                span = after[-1][0] - first
                n = after[-1][1] - after[0][1]
                print(f"{name}: {n} volume frames in {span:.1f} s while orbiting: "
                      f"{1000 * span / max(n, 1):.0f} ms per frame")
