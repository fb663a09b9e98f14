#!/usr/bin/env python3
"""The dashboard and the alert rules against a live Prometheus, driven by
deploy/container-test.sh (Grafana itself cannot run there).

  promlive.py rules-copy OUT            a TEST copy of alerts.yml with every
                                        `for:` shortened to 5s (expressions and
                                        thresholds unchanged)
  promlive.py eval URL                  evaluate every dashboard query and
                                        every alert rule's signal; exit 1 when
                                        one returns no series
  promlive.py alert URL NAME TIMEOUT_S  wait until alert NAME is pending or
                                        firing; prints its state and labels
  promlive.py value URL EXPR            the sum of EXPR's samples (0 if none)

An alert expression such as `ratio > 0.2 and rate > 1` returns series only
while it fires, so what must return series is its *signal*: the expression
with each top-level threshold comparison removed (`ratio`, `rate`), and
`absent(x == 1)` read as `x`. The dashboard queries are taken with Grafana's
variables substituted as check.py does (`$__rate_interval` = 5m, `$var` = .*).
"""
from __future__ import annotations

import json
import math
import sys
import time
import urllib.parse
import urllib.request
from pathlib import Path

import yaml

from check import ALERTS, after_string, load_yaml_docs, queries

TEST_FOR = "5s"
COMPARISONS = ("==", "!=", ">=", "<=", ">", "<")
SET_OPS = ("and", "or", "unless")


def api(url: str, path: str, params: dict | None = None) -> dict:
    q = ("?" + urllib.parse.urlencode(params)) if params else ""
    with urllib.request.urlopen(f"{url.rstrip('/')}{path}{q}", timeout=10) as r:
        body = json.load(r)
    if body.get("status") != "success":
        raise RuntimeError(f"{path}: {body.get('errorType')}: {body.get('error')}")
    return body["data"]


def query(url: str, expr: str) -> list[float]:
    """Values of the series EXPR returns now (a scalar counts as one)."""
    data = api(url, "/api/v1/query", {"query": expr})
    if data["resultType"] in ("scalar", "string"):
        return [float(data["result"][1])]
    return [float(s["value"][1]) for s in data["result"]]


def top_level(expr: str):
    """(index, token) of operators outside (), {}, [] and string literals."""
    depth, i, n = 0, 0, len(expr)
    while i < n:
        ch = expr[i]
        if ch in "\"'`":
            i = after_string(expr, i)
            continue
        if ch in "({[":
            depth += 1
        elif ch in ")}]":
            depth -= 1
        elif depth == 0:
            for op in COMPARISONS:
                if expr.startswith(op, i):
                    yield i, op
                    i += len(op) - 1
                    break
            else:
                for op in SET_OPS:
                    before = expr[i - 1] if i else " "
                    after = expr[i + len(op)] if i + len(op) < n else " "
                    if expr.startswith(op, i) and before.isspace() and after.isspace():
                        yield i, op
                        i += len(op) - 1
                        break
        i += 1


def unwrap(expr: str) -> str:
    """EXPR without parentheses that enclose all of it."""
    e = expr.strip()
    while e.startswith("(") and e.endswith(")"):
        depth = 0
        for i, ch in enumerate(e):
            depth += ch == "("
            depth -= ch == ")"
            if depth == 0 and i < len(e) - 1:
                return e
        e = e[1:-1].strip()
    return e


def is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def signals(expr: str) -> list[str]:
    """The expressions that must return series for EXPR to be able to fire."""
    e = unwrap(expr)
    ops = list(top_level(e))
    for i, op in ops:
        if op in SET_OPS:
            return signals(e[:i]) + signals(e[i + len(op):])
    for i, op in reversed(ops):
        lhs, rhs = e[:i], e[i + len(op):]
        rhs = rhs.strip()
        if rhs.startswith("bool"):
            rhs = rhs[4:].strip()
        if is_number(rhs):
            return signals(lhs)
    if e.startswith("absent(") and e.endswith(")"):
        return signals(e[len("absent("):-1])
    return [e]


def cmd_rules_copy(out: str) -> int:
    doc = load_yaml_docs(ALERTS)[0]
    n = 0
    for g in doc.get("groups", []):
        for r in g.get("rules", []):
            if "for" in r:
                r["for"] = TEST_FOR
                n += 1
    Path(out).write_text(
        "# TEST COPY of deploy/prometheus/alerts.yml written by deploy/container-test.sh:\n"
        f"# every `for:` is {TEST_FOR} so that the fault scenarios reach `firing` in seconds.\n"
        "# Expressions and thresholds are those of the real file.\n"
        + yaml.safe_dump(doc, sort_keys=False, width=1000))
    print(f"  wrote {out}: {n} rules with for: {TEST_FOR}")
    return 0


def cmd_eval(url: str) -> int:
    rows, failed = [], 0
    counts = {"dashboard": 0, "alert": 0}
    for where, expr in queries():
        kind = "alert" if where.startswith("alert ") else "dashboard"
        exprs = signals(expr) if kind == "alert" else [expr]
        counts[kind] += 1
        for e in exprs:
            try:
                vals = query(url, e)
                err = ""
            except Exception as ex:  # noqa: BLE001
                vals, err = [], str(ex)
            finite = [v for v in vals if math.isfinite(v)]
            nonzero = sum(1 for v in finite if v != 0)
            ok = bool(vals)
            failed += not ok
            rows.append((ok, where, len(vals), len(finite), nonzero, e, err))
    for ok, where, n, finite, nonzero, e, err in rows:
        print(f"  {'ok  ' if ok else 'FAIL'}  {where}: {n} series ({finite} finite, {nonzero} non-zero)"
              + (f"  [{e}]" if not ok or where.startswith("alert") else "") + (f" {err}" if err else ""))
    firing = api(url, "/api/v1/alerts")["alerts"]
    print(f"  alerts active now: {sorted({(a['labels']['alertname'], a['state']) for a in firing})}")
    nz = sum(1 for r in rows if r[4] > 0)
    print(f"expressions: {counts['dashboard']} dashboard, {counts['alert']} alert rules "
          f"({len(rows)} queries, {len(rows) - failed} with data, {nz} with a non-zero value)")
    return 1 if failed else 0


def cmd_alert(url: str, name: str, timeout: float) -> int:
    t0 = time.monotonic()
    while True:
        active = [a for a in api(url, "/api/v1/alerts")["alerts"] if a["labels"].get("alertname") == name]
        if active:
            a = max(active, key=lambda a: a["state"] == "firing")
            labels = {k: v for k, v in a["labels"].items() if k not in ("alertname", "severity")}
            print(f"  {name}: {a['state']} after {time.monotonic() - t0:.1f} s {labels}")
            return 0
        if time.monotonic() - t0 > timeout:
            print(f"  FAIL  {name}: neither pending nor firing after {timeout:.0f} s")
            for where, expr in queries():
                if where == f"alert {name}":
                    for e in signals(expr):
                        data = api(url, "/api/v1/query", {"query": e})["result"]
                        print(f"    {' '.join(e.split())} = {[(r['metric'], r['value'][1]) for r in data]}")
            return 1
        time.sleep(0.5)


def cmd_value(url: str, expr: str) -> int:
    v = sum((v for v in query(url, expr) if math.isfinite(v)), 0.0)
    print(int(v) if v.is_integer() else f"{v:.6g}")
    return 0


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__)
        return 2
    cmd, args = argv[0], argv[1:]
    if cmd == "rules-copy" and len(args) == 1:
        return cmd_rules_copy(args[0])
    if cmd == "eval" and len(args) == 1:
        return cmd_eval(args[0])
    if cmd == "alert" and len(args) == 3:
        return cmd_alert(args[0], args[1], float(args[2]))
    if cmd == "value" and len(args) == 2:
        return cmd_value(args[0], args[1])
    print(__doc__)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
