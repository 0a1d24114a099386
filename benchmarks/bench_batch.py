"""Section c (``batch``) of ``bench_plant.py``: ``PlantBatch`` throughput in 5 ms control
periods with 1 and 2 numba threads (round-robin), against a single ``Plant``, and the check that
every plant of the batch ends in the same state as the single plant. See ``benchmarks/README.md``.

    python benchmarks/bench_batch.py [--quick] [--out DIR]   # = bench_plant.py --only batch
"""
from __future__ import annotations

import sys
import time

import numba
import numpy as np

from common import fmt_table, g, stats, timeit
from pneugym import Plant, PlantBatch, thesis_rig


def bench_batch(reps, quick):
    sizes = (64,) if quick else (64, 256)
    period, t_sim = 0.005, 1.5
    nper = int(round(t_sim / period))
    res = {"control_period_s": period, "simulated_s": t_sim, "control_periods": nper, "sizes": {}}
    nthreads_avail = numba.config.NUMBA_NUM_THREADS
    threads = [t for t in (1, 2) if t <= nthreads_avail]
    # single plant, same control loop, for comparison
    pl = Plant(thesis_rig(2.5))

    def single():
        for _ in range(nper):
            pl.advance(period, 1)

    t_single = timeit(single, pl.reset, reps)
    res["single_plant_control_loop"] = {**stats(t_single),
                                        "plant_s_per_wall_s": t_sim / float(np.median(t_single)),
                                        "plant_steps_per_s": nper / float(np.median(t_single)),
                                        "us_per_advance_5ms_call": float(np.median(t_single)) / nper * 1e6}
    y_single = pl.y.copy()
    for B in sizes:
        batch = PlantBatch([thesis_rig(2.5)] * B)
        cmds = np.ones(B)

        def run_batch():
            for _ in range(nper):
                batch.advance(cmds, period)

        entry = {}
        times = {nt: [] for nt in threads}
        for nt in threads:  # warm-up (compiles / starts the thread pool)
            numba.set_num_threads(nt)
            batch.reset()
            run_batch()
        for _ in range(max(3, reps // 2)):  # interleaved, so that load from others hits both alike
            for nt in threads:
                numba.set_num_threads(nt)
                batch.reset()
                t0 = time.perf_counter()
                run_batch()
                times[nt].append(time.perf_counter() - t0)
        for nt in threads:
            t = times[nt]
            entry[f"{nt}_threads"] = {**stats(t), "plant_s_per_wall_s": B * t_sim / float(np.median(t)),
                                      "plant_steps_per_s": B * nper / float(np.median(t)),
                                      "plant_steps_per_s_min_time": B * nper / float(np.min(t))}
        numba.set_num_threads(nthreads_avail)
        if len(threads) == 2:
            entry["speedup_2_over_1"] = (entry["1_threads"]["median_s"] / entry["2_threads"]["median_s"])
            # from the fastest repeats: what 2 threads give when no other process takes a core
            entry["speedup_2_over_1_min_times"] = (entry["1_threads"]["min_s"] / entry["2_threads"]["min_s"])
        entry["max_abs_diff_vs_single_plant"] = float(np.max(np.abs(batch.Y - y_single[None, :])))
        entry["batch_over_single_throughput_1_thread"] = (
            entry["1_threads"]["plant_s_per_wall_s"] / res["single_plant_control_loop"]["plant_s_per_wall_s"])
        res["sizes"][str(B)] = entry
    try:
        res["threading_layer"] = numba.threading_layer()
    except ValueError:
        res["threading_layer"] = None
    return res


def report_batch(bt):
    """Text block of section c (batch) for the report."""
    out = []
    sp = bt["single_plant_control_loop"]
    rows = [["single Plant, 5 ms loop", "1", "-", g(sp["median_s"] * 1e3, 4), g(sp["plant_s_per_wall_s"], 4),
             g(sp["plant_steps_per_s"] / 1e3, 4), g(sp["us_per_advance_5ms_call"], 3), "-", "-", "-"]]
    for B, e in bt["sizes"].items():
        for key in ("1_threads", "2_threads"):
            if key not in e:
                continue
            rows.append([f"PlantBatch B={B}", B, key.split("_")[0], g(e[key]["median_s"] * 1e3, 4),
                         g(e[key]["plant_s_per_wall_s"], 4), g(e[key]["plant_steps_per_s"] / 1e3, 4),
                         g(1e6 / e[key]["plant_steps_per_s"], 3),
                         g(e.get("speedup_2_over_1"), 3) if key == "2_threads" else "",
                         g(e.get("speedup_2_over_1_min_times"), 3) if key == "2_threads" else "",
                         g(e["max_abs_diff_vs_single_plant"], 3) if key == "1_threads" else ""])
    out.append(fmt_table(["case", "B", "threads", "wall [ms]", "plant-s / wall-s", "plant-steps/s [k]",
                          "us / plant-step", "speed-up 2/1",
                          "speed-up 2/1 (min times)", "max|Y-Y_single|"], rows,
                         f"c. Batched kernel: 1.5 s simulated in 5 ms control periods "
                         f"(threading layer {bt.get('threading_layer')}); a plant-step = one 5 ms "
                         f"period of one plant (Plant.advance(0.005, 1) / PlantBatch.advance(cmds, 0.005))"))
    return out


if __name__ == "__main__":
    import bench_plant

    bench_plant.main(["--only", "batch", *sys.argv[1:]])
