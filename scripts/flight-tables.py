#!/usr/bin/env python3
"""Markdown tables from `planet-bench flight` summary.json files.

Usage: scripts/flight-tables.py OUT_DIR [OUT_DIR ...]

One table per summary: a row per (link, policy) with the error integrals,
the time to the tolerance after each stop, bytes, needed/delivered,
relevant and wasted ratios; then, per link, `ours` over `cesium` for the
integrals (the issue's goal is at most 0.5 on `error_integral_px_s`, the
per-pixel mean; the block mean is shown beside it), the floor (the same
flight with every request answered at once), each policy's excess over it,
the ratio a policy with no excess would reach (floor / Cesium's integral:
where it is above 0.5 no policy at this tolerance meets the goal), and the
lower bound on the time to the tolerance at a stop at t = 0.
"""
import json
import sys


def fmt_stop(v):
    return "—" if v is None else f"{v:.2f}"


def main():
    for d in sys.argv[1:]:
        with open(f"{d}/summary.json") as f:
            rows = json.load(f)
        if not rows:
            continue
        print(f"**{rows[0]['trajectory']}** (`{d}`; tolerance {rows[0]['max_sse_px']} px,"
              f" bytes needed along the path {rows[0]['needed_bytes'] / 1e6:.1f} MB)\n")
        print("| link | policy | ∫ mean SSE dt per pixel (px·s) | ∫ max SSE dt | ∫ block-mean SSE dt |"
              " to tolerance after each stop (s) | MB received | needed / delivered |"
              " relevant | wasted (dropped) | requests / cancels |")
        print("|---|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            stops = ", ".join(f"{a:.0f}: {fmt_stop(b)}" for a, b in
                              zip(r["stops_s"], r["time_to_1px_after_stops_s"]))
            nod = r["needed_over_delivered"]
            print(f"| {r['link']} | {r['policy']} | {r['error_integral_px_s']:.0f} |"
                  f" {r['max_sse_integral_px_s']:.0f} | {r['block_error_integral_px_s']:.0f} |"
                  f" {stops} | {r['bytes'] / 1e6:.2f} | {'—' if nod is None else f'{nod:.1f}×'} |"
                  f" {100 * r['relevant_ratio']:.2f} % | {100 * r['wasted_ratio']:.2f} % ({100 * r.get('dropped_ratio', 0):.2f} %) |"
                  f" {r['requests']} / {r['cancels']} |")
        print()
        by = {(r["link"], r["policy"]): r for r in rows}
        links = list(dict.fromkeys(r["link"] for r in rows))
        if any((l, "cesium") in by and (l, "ours") in by for l in links):
            print("| link | ours / cesium: ∫ mean SSE per pixel | floor ∫ (px·s) | excess ∫, ours / cesium (px·s) |"
                  " excess ratio | best ratio any policy reaches | ∫ max SSE | ∫ block-mean SSE |"
                  " stops (ours / cesium, s) | start's lower bound (s) |")
            print("|---|---|---|---|---|---|---|---|---|---|")
            for l in links:
                o, c = by.get((l, "ours")), by.get((l, "cesium"))
                if not o or not c:
                    continue
                q = lambda k: o[k] / c[k] if c[k] else float("nan")
                stops = ", ".join(f"{fmt_stop(a)} / {fmt_stop(b)}" for a, b in
                                  zip(o["time_to_1px_after_stops_s"],
                                      c["time_to_1px_after_stops_s"]))
                f = o.get("floor_error_integral_px_s")
                if f is None:
                    floor = excess = eratio = best = "—"
                else:
                    eo, ec = o["excess_error_integral_px_s"], c["excess_error_integral_px_s"]
                    floor = f"{f:.1f}"
                    excess = f"{eo:.1f} / {ec:.1f}"
                    eratio = f"{eo / ec:.2f}" if ec > 0 else "—"
                    # A policy with no excess at all: the floor over Cesium's integral.
                    best = f"{f / c['error_integral_px_s']:.2f}"
                b = o.get("start_lower_bound_s")
                print(f"| {l} | {q('error_integral_px_s'):.2f} | {floor} | {excess} | {eratio} | {best} |"
                      f" {q('max_sse_integral_px_s'):.2f} |"
                      f" {q('block_error_integral_px_s'):.2f} | {stops} | {'—' if b is None else f'{b:.2f}'} |")
            print()


if __name__ == "__main__":
    main()
