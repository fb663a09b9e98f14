#!/usr/bin/env python3
"""Offline checks of the deployment files, driven by deploy/check.sh.

Each subcommand prints one line per check ("ok", "FAIL", "WARN", "note") and
exits 1 when any check failed:

  check.py dockerfile            Dockerfile and .dockerignore structure
  check.py compose               deploy/compose.yaml structure and mounts
  check.py grafana               dashboard JSON and provisioning
  check.py config                deploy/server.toml and the k8s ConfigMap copy
  check.py k8s                   manifests: kustomization, cross-references
  check.py promql-rules OUT      write dashboard queries as a rule file for promtool
  check.py metrics [SCRAPE]      queried names/labels against metrics-contract.txt
                                 and, if given, a /metrics scrape
  check.py probes                the Deployment's probes: KIND PATH PORT per line
  check.py grace                 the shortest grace period of k8s and compose (s)
  check.py agree IMAGE_JSON KIB_PER_CONNECTION DRAIN_MS
                                 image (podman image inspect), k8s and compose
                                 agree; resources cover measured memory
"""
from __future__ import annotations

import json
import re
import sys
from pathlib import Path

try:
    import tomllib  # Python >= 3.11
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib  # type: ignore[no-redef]

import yaml

DEPLOY = Path(__file__).resolve().parent
ROOT = DEPLOY.parent
DASHBOARD = DEPLOY / "grafana" / "dashboards" / "planet-server.json"
ALERTS = DEPLOY / "prometheus" / "alerts.yml"
CONTRACT = DEPLOY / "metrics-contract.txt"
K8S = DEPLOY / "k8s"


class Checker:
    def __init__(self, section: str) -> None:
        self.section = section
        self.failed = 0

    def ok(self, cond: bool, what: str, detail: str = "") -> bool:
        if cond:
            print(f"  ok    {what}")
        else:
            self.failed += 1
            print(f"  FAIL  {what}" + (f": {detail}" if detail else ""))
        return cond

    def warn(self, what: str) -> None:
        print(f"  WARN  {what}")

    def note(self, what: str) -> None:
        print(f"  note  {what}")

    def done(self) -> int:
        return 1 if self.failed else 0


def rel(p: Path) -> str:
    try:
        return str(p.relative_to(ROOT))
    except ValueError:
        return str(p)


def load_yaml_docs(path: Path) -> list:
    with path.open() as f:
        return [d for d in yaml.safe_load_all(f) if d is not None]


# --------------------------------------------------------------------------
# Dockerfile


def dockerfile_instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) with line continuations joined, comments dropped."""
    out: list[tuple[str, str]] = []
    buf = ""
    for raw in text.splitlines():
        line = raw.strip()
        if not buf and (not line or line.startswith("#")):
            continue
        if buf and line.startswith("#"):
            continue
        if line.endswith("\\"):
            buf += line[:-1] + " "
            continue
        buf += line
        if buf.strip():
            word, _, rest = buf.strip().partition(" ")
            out.append((word.upper(), rest.strip()))
        buf = ""
    return out


def dockerfile_stages(ins: list[tuple[str, str]]) -> tuple[dict[str, str], list[dict]]:
    """Global ARG defaults and the stages: {name, base (ARGs substituted), ins}."""
    args: dict[str, str] = {}
    stages: list[dict] = []
    for w, a in ins:
        if w == "FROM":
            m = re.match(r"(\S+)(?:\s+AS\s+(\S+))?", a, re.I)
            base = re.sub(r"\$\{?(\w+)\}?", lambda v: args.get(v.group(1), v.group(0)), m.group(1) if m else a)
            stages.append({"name": (m.group(2) or "") if m else "", "base": base, "ins": []})
        elif stages:
            stages[-1]["ins"].append((w, a))
        elif w == "ARG":
            k, _, v = a.partition("=")
            args[k.strip()] = v.strip()
    return args, stages


def stage_chain(stages: list[dict], name: str) -> list[tuple[str, str]]:
    """Instructions of stage NAME with those of the stages it is built FROM."""
    by_name = {st["name"]: st for st in stages}
    st = by_name.get(name)
    if st is None:
        return []
    return stage_chain(stages, st["base"]) + st["ins"]


def cmd_dockerfile() -> int:
    c = Checker("dockerfile")
    path = ROOT / "Dockerfile"
    if not c.ok(path.is_file(), "Dockerfile exists"):
        return c.done()
    ins = dockerfile_instructions(path.read_text())
    args, stages = dockerfile_stages(ins)
    names = [st["name"] for st in stages]
    c.ok(len(stages) >= 2, "multi-stage build", f"{len(stages)} FROM")
    builder = next((st for st in stages if st["name"] == "builder"), None)
    c.ok(builder is not None and builder["base"] == "rust:1-bookworm",
         "builder stage: FROM ${RUST_IMAGE} AS builder, RUST_IMAGE defaults to rust:1-bookworm",
         builder["base"] if builder else "no builder stage")
    c.ok(bool(stages) and stages[-1]["name"] == "runtime", "the last stage (default target) is runtime", str(names))
    base = next((st for st in stages if st["name"] == "runtime-base"), None)
    c.ok(base is not None and base["base"] == "debian:bookworm-slim",
         "runtime-base: FROM ${RUNTIME_IMAGE}, RUNTIME_IMAGE defaults to debian:bookworm-slim",
         base["base"] if base else "no runtime-base stage")
    for st in stages:
        if st["name"] in ("runtime", "runtime-prebuilt"):
            c.ok(st["base"] == "runtime-base", f"{st['name']} is built FROM runtime-base", st["base"])
    runs = " ".join(a for w, a in ins if w == "RUN")
    c.ok("cargo build --release --locked -p planet-server-bin -p planet-preprocess" in runs,
         "builder runs cargo build --release --locked -p planet-server-bin -p planet-preprocess")
    copies = {st["name"]: " ".join(a for w, a in st["ins"] if w == "COPY") for st in stages}
    c.ok("--from=builder" in copies.get("runtime", ""), "runtime copies the binaries from the builder stage")
    c.ok("--from=prebuilt" in copies.get("runtime-prebuilt", ""),
         "runtime-prebuilt copies the binaries from the build context named prebuilt")
    for target in ("runtime", "runtime-prebuilt"):
        cp = copies.get(target, "")
        c.ok("planet-server" in cp and "planet-build" in cp and "/usr/local/bin" in cp,
             f"{target}: planet-server and planet-build copied to /usr/local/bin")
    last = stage_chain(stages, "runtime")
    installs = re.findall(r"apt-get install ([^&;]*)", " ".join(a for w, a in last if w == "RUN"))
    pkgs = {t for s in installs for t in s.split() if not t.startswith("-")}
    c.ok(pkgs == {"ca-certificates"}, "runtime installs ca-certificates only", f"installs {sorted(pkgs)}")
    users = [a for w, a in last if w == "USER"]
    c.ok(bool(users) and users[-1].split(":")[0] in ("10001", "planet"), "runs as non-root user planet (10001)",
         f"USER {users[-1] if users else '(none)'}")
    c.ok(re.search(r"useradd\b[^&]*--uid 10001\b[^&]*\bplanet\b", " ".join(a for w, a in last if w == "RUN")) is not None,
         "user planet created with uid 10001")
    hc = [a for w, a in last if w == "HEALTHCHECK"]
    c.ok(bool(hc) and "http://127.0.0.1:9100/healthz" in hc[-1], "HEALTHCHECK probes http://127.0.0.1:9100/healthz")
    expose = " ".join(a for w, a in last if w == "EXPOSE").split()
    c.ok("4433/udp" in expose and ("9100/tcp" in expose or "9100" in expose), "EXPOSE 4433/udp 9100/tcp", str(expose))
    vols = " ".join(a for w, a in last if w == "VOLUME")
    c.ok("/data" in vols and "/etc/planet" in vols, "VOLUME /data and /etc/planet")
    cmds = [a for w, a in last if w == "CMD"]
    try:
        cmd = json.loads(cmds[-1]) if cmds else []
    except json.JSONDecodeError:
        cmd = []
    c.ok(cmd == ["planet-server", "--config", "/etc/planet/server.toml"],
         "CMD planet-server --config /etc/planet/server.toml (exec form)", str(cmd))

    di = ROOT / ".dockerignore"
    if c.ok(di.is_file(), ".dockerignore exists"):
        entries = {l.strip().rstrip("/") for l in di.read_text().splitlines() if l.strip() and not l.startswith("#")}
        for need in ("target", ".git", "out"):
            c.ok(need in entries, f".dockerignore excludes {need}")
    return c.done()


# --------------------------------------------------------------------------
# compose


def bind_mounts(service: dict) -> list[tuple[str, str, bool]]:
    """(source, target, read_only) of bind mounts (short or long syntax)."""
    out = []
    for v in service.get("volumes", []) or []:
        if isinstance(v, str):
            parts = v.split(":")
            if len(parts) >= 2 and (parts[0].startswith(".") or parts[0].startswith("/")):
                out.append((parts[0], parts[1], len(parts) > 2 and "ro" in parts[2].split(",")))
        elif isinstance(v, dict) and v.get("type") == "bind":
            out.append((v["source"], v["target"], bool(v.get("read_only"))))
    return out


def cmd_compose() -> int:
    c = Checker("compose")
    path = DEPLOY / "compose.yaml"
    try:
        doc = load_yaml_docs(path)[0]
    except Exception as e:  # noqa: BLE001
        c.ok(False, f"{rel(path)} parses as YAML", str(e))
        return c.done()
    c.ok(True, f"{rel(path)} parses as YAML")
    services = doc.get("services") or {}
    for name in ("planet-server", "prometheus", "grafana"):
        c.ok(name in services, f"service {name} defined")
    if c.failed:
        return c.done()

    ps = services["planet-server"]
    build = ps.get("build") or {}
    ctx = (DEPLOY / build.get("context", ".")).resolve()
    c.ok(ctx == ROOT, "planet-server builds from the repository root", str(ctx))
    c.ok((ctx / build.get("dockerfile", "Dockerfile")).resolve() == ROOT / "Dockerfile", "planet-server uses ../Dockerfile")
    ports = [str(p) for p in ps.get("ports", [])]
    c.ok(any(p.endswith("4433/udp") for p in ports), "planet-server publishes 4433/udp", str(ports))
    c.ok(any(re.search(r"(^|:)9100(/tcp)?$", p) for p in ports), "planet-server publishes 9100", str(ports))
    mounts = bind_mounts(ps)
    targets = {t for _, t, _ in mounts}
    c.ok("/data" in targets, "planet-server mounts /data")
    c.ok(any(t.startswith("/etc/planet") for t in targets), "planet-server mounts config under /etc/planet")
    c.ok(all(ro for _, _, ro in mounts), "planet-server mounts are read-only",
         str([t for _, t, ro in mounts if not ro]))
    c.ok(ps.get("read_only") is True, "planet-server root filesystem read-only")

    prom_mounts = {t: s for s, t, _ in bind_mounts(services["prometheus"])}
    c.ok(prom_mounts.get("/etc/prometheus/prometheus.yml") == "./prometheus/prometheus.yml",
         "prometheus mounts prometheus/prometheus.yml")
    c.ok(prom_mounts.get("/etc/prometheus/alerts.yml") == "./prometheus/alerts.yml",
         "prometheus mounts prometheus/alerts.yml")
    prom_cfg = load_yaml_docs(DEPLOY / "prometheus" / "prometheus.yml")[0]
    for rf in prom_cfg.get("rule_files", []):
        target = rf if rf.startswith("/") else "/etc/prometheus/" + rf
        c.ok(target in prom_mounts, f"rule file {rf} is mounted into the prometheus container")
    scrape_targets = [t for sc in prom_cfg.get("scrape_configs", []) if sc.get("job_name") == "planet-server"
                      for st in sc.get("static_configs", []) for t in st.get("targets", [])]
    c.ok("planet-server:9100" in scrape_targets, "prometheus scrapes planet-server:9100 as job planet-server",
         str(scrape_targets))

    graf_mounts = {t: s for s, t, _ in bind_mounts(services["grafana"])}
    c.ok(graf_mounts.get("/etc/grafana/provisioning") == "./grafana/provisioning", "grafana mounts provisioning")
    dash_target = [t for t, s in graf_mounts.items() if s == "./grafana/dashboards"]
    c.ok(bool(dash_target), "grafana mounts grafana/dashboards")
    prov = load_yaml_docs(DEPLOY / "grafana" / "provisioning" / "dashboards" / "dashboards.yaml")[0]
    paths = [p.get("options", {}).get("path") for p in prov.get("providers", [])]
    c.ok(bool(dash_target) and dash_target[0] in paths, "dashboard provider path matches the dashboards mount",
         f"{paths} vs {dash_target}")
    ds = load_yaml_docs(DEPLOY / "grafana" / "provisioning" / "datasources" / "prometheus.yaml")[0]
    urls = [d.get("url", "") for d in ds.get("datasources", [])]
    c.ok(any(u.startswith("http://prometheus:9090") for u in urls), "grafana datasource points at the prometheus service", str(urls))

    local_only = set()
    gi = DEPLOY / ".gitignore"
    if gi.is_file():
        local_only = {"./" + l.strip().strip("/") for l in gi.read_text().splitlines() if l.strip() and not l.startswith("#")}
    for svc_name, svc in services.items():
        for src, tgt, _ in bind_mounts(svc):
            if src in local_only:
                c.note(f"{svc_name}: {src} -> {tgt} is local-only input ({'present' if (DEPLOY / src).exists() else 'absent here'}, see docs/DEPLOY.md)")
            else:
                c.ok((DEPLOY / src).exists(), f"{svc_name}: bind source {src} exists")
    return c.done()


# --------------------------------------------------------------------------
# Grafana

REQUIRED_PANELS = [
    "connections", "request rate by tenant and outcome", "bytes sent per second", "latency percentiles",
    "in flight", "validation failures", "cancelled", "handshake failures", "cpu", "memory",
]


def walk_panels(panels: list) -> list:
    out = []
    for p in panels or []:
        out.append(p)
        out.extend(walk_panels(p.get("panels", [])))
    return out


def cmd_grafana() -> int:
    c = Checker("grafana")
    try:
        dash = json.loads(DASHBOARD.read_text())
    except Exception as e:  # noqa: BLE001
        c.ok(False, f"{rel(DASHBOARD)} is valid JSON", str(e))
        return c.done()
    c.ok(True, f"{rel(DASHBOARD)} is valid JSON")
    c.ok(bool(dash.get("uid")) and bool(dash.get("title")), "dashboard has uid and title")
    panels = walk_panels(dash.get("panels", []))
    ids = [p.get("id") for p in panels]
    c.ok(len(ids) == len(set(ids)) and None not in ids, "panel ids unique")
    c.ok(all("gridPos" in p for p in panels), "every panel has a gridPos")
    titles = [p.get("title", "").lower() for p in panels if p.get("type") != "row"]
    for need in REQUIRED_PANELS:
        c.ok(any(need in t for t in titles), f"panel '{need}' present")
    ds_prov = load_yaml_docs(DEPLOY / "grafana" / "provisioning" / "datasources" / "prometheus.yaml")[0]
    uids = {d.get("uid") for d in ds_prov.get("datasources", [])}
    c.ok(bool(uids - {None}), "provisioned datasource has a fixed uid", str(uids))
    var_names = {v.get("name") for v in dash.get("templating", {}).get("list", [])}
    bad = []
    for p in panels:
        for obj in [p] + list(p.get("targets", [])):
            d = obj.get("datasource")
            if isinstance(d, dict) and d.get("type") == "prometheus":
                u = d.get("uid", "")
                m = re.fullmatch(r"\$\{?(\w+)\}?", u)
                if not ((m and m.group(1) in var_names) or u in uids):
                    bad.append(f"panel {p.get('id')}: uid {u}")
    c.ok(not bad, "panel datasources reference the provisioned datasource or a dashboard variable", "; ".join(bad))
    c.ok(all(t.get("expr") for p in panels if p.get("type") != "row" for t in p.get("targets", [])),
         "every panel target has a PromQL expr")
    prov = load_yaml_docs(DEPLOY / "grafana" / "provisioning" / "dashboards" / "dashboards.yaml")[0]
    c.ok(prov.get("apiVersion") == 1 and bool(prov.get("providers")), "dashboard provider file parses (apiVersion 1)")
    c.ok(ds_prov.get("apiVersion") == 1 and bool(ds_prov.get("datasources")), "datasource file parses (apiVersion 1)")
    return c.done()


# --------------------------------------------------------------------------
# PromQL extraction

GRAFANA_DURATION_VARS = re.compile(r"\$\{?__(rate_interval|interval|range)\}?")
GRAFANA_VARS = re.compile(r"\$\{(\w+)(?::\w+)?\}|\$(\w+)")


def grafana_to_promql(expr: str) -> str:
    expr = GRAFANA_DURATION_VARS.sub("5m", expr)
    return GRAFANA_VARS.sub(".*", expr)


def template_query_expr(q: str) -> str | None:
    """The PromQL inside a Grafana Prometheus variable query, if any."""
    q = q.strip()
    m = re.fullmatch(r"label_values\((.*),\s*\w+\s*\)", q, re.S)
    if m:
        return m.group(1)
    m = re.fullmatch(r"query_result\((.*)\)", q, re.S)
    if m:
        return m.group(1)
    m = re.fullmatch(r"metrics\((.*)\)", q, re.S)
    if m:
        return None
    return None


def queries() -> list[tuple[str, str]]:
    """(where, PromQL) of every query of the dashboard (Grafana variables
    substituted) and of the alert rules."""
    out: list[tuple[str, str]] = []
    dash = json.loads(DASHBOARD.read_text())
    for p in walk_panels(dash.get("panels", [])):
        for t in p.get("targets", []):
            if t.get("expr"):
                out.append((f"dashboard panel '{p.get('title')}' {t.get('refId', '')}", grafana_to_promql(t["expr"])))
    for v in dash.get("templating", {}).get("list", []):
        if v.get("type") == "query":
            q = v.get("query")
            q = q.get("query", "") if isinstance(q, dict) else (q or "")
            e = template_query_expr(q)
            if e:
                out.append((f"dashboard variable ${v.get('name')}", grafana_to_promql(e)))
    for a in dash.get("annotations", {}).get("list", []):
        if a.get("expr"):
            out.append((f"dashboard annotation '{a.get('name')}'", grafana_to_promql(a["expr"])))
    for g in load_yaml_docs(ALERTS)[0].get("groups", []):
        for r in g.get("rules", []):
            out.append((f"alert {r.get('alert') or r.get('record')}", r["expr"]))
    return out


def cmd_promql_rules(out_path: str) -> int:
    """Dashboard queries as recording rules, so promtool parses them (alert
    expressions are parsed by promtool check rules on alerts.yml itself)."""
    dash = [expr for where, expr in queries() if where.startswith("dashboard")]
    rules = [{"record": f"dashboard:query_{i}:check", "expr": expr} for i, expr in enumerate(dash)]
    Path(out_path).write_text(yaml.safe_dump({"groups": [{"name": "dashboard-queries", "rules": rules}]},
                                             sort_keys=False, width=1000))
    print(f"  wrote {len(rules)} dashboard queries to {out_path}")
    return 0


IDENT = re.compile(r"[a-zA-Z_:][a-zA-Z0-9_:]*")
MATCHER = re.compile(r'\s*([a-zA-Z_]\w*)\s*(=~|!~|!=|=)\s*"((?:[^"\\]|\\.)*)"\s*,?')


def after_string(expr: str, i: int) -> int:
    """Index just past the PromQL string literal that starts at EXPR[i]."""
    j = i + 1
    while j < len(expr) and expr[j] != expr[i]:
        j += 2 if expr[j] == "\\" else 1
    return j + 1


def selectors(expr: str) -> list[tuple[str, list[tuple[str, str, str]]]]:
    """(metric name, [(label, op, value)]) of every selector naming a planet_*,
    process_* or up series. String literals are skipped."""
    out = []
    i, n = 0, len(expr)
    while i < n:
        ch = expr[i]
        if ch in "\"'`":
            i = after_string(expr, i)
            continue
        if ch == "{":  # a bare {..} selector or a matcher block we did not attach: skip it
            depth_end = expr.find("}", i)
            i = n if depth_end < 0 else depth_end + 1
            continue
        m = IDENT.match(expr, i)
        if not m:
            i += 1
            continue
        name = m.group(0)
        j = m.end()
        prev = expr[i - 1] if i > 0 else " "
        if prev.isalnum() or prev in "_:.":
            i = j
            continue
        k = j
        while k < n and expr[k].isspace():
            k += 1
        is_call = k < n and expr[k] == "("
        if (name.startswith("planet_") or name.startswith("process_") or name == "up") and not is_call:
            matchers: list[tuple[str, str, str]] = []
            if k < n and expr[k] == "{":
                end = k + 1
                while end < n and expr[end] != "}":
                    if expr[end] == '"':
                        end += 1
                        while end < n and expr[end] != '"':
                            end += 2 if expr[end] == "\\" else 1
                    end += 1
                body = expr[k + 1:end]
                pos = 0
                while pos < len(body.rstrip()):
                    mm = MATCHER.match(body, pos)
                    if not mm:
                        matchers.append(("?", "?", body[pos:]))
                        break
                    matchers.append((mm.group(1), mm.group(2), mm.group(3)))
                    pos = mm.end()
                j = end + 1
            out.append((name, matchers))
        i = j
    return out


def load_contract() -> dict[str, dict]:
    contract: dict[str, dict] = {}
    for line in CONTRACT.read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        name, typ, *labels = line.split()
        lab: dict[str, set[str] | None] = {}
        for l in labels:
            k, _, vals = l.partition("=")
            lab[k] = set(vals.split("|")) if vals else None
        contract[name] = {"type": typ, "labels": lab}
    return contract


HIST_SUFFIXES = ("_bucket", "_sum", "_count")


def resolve(name: str, contract: dict) -> tuple[str | None, str]:
    """Contract family of a queried series name, and the suffix used."""
    if name in contract:
        return name, ""
    for s in HIST_SUFFIXES:
        if name.endswith(s) and contract.get(name[: -len(s)], {}).get("type") == "histogram":
            return name[: -len(s)], s
    return None, ""


def parse_scrape(path: Path) -> tuple[dict[str, str], dict[str, dict[str, set[str]]]]:
    """Families ({name: type}) and label values per sample name of a text
    exposition scrape."""
    types: dict[str, str] = {}
    labels: dict[str, dict[str, set[str]]] = {}
    sample = re.compile(r"^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{(.*)\})?\s+\S+")
    for line in path.read_text(errors="replace").splitlines():
        if line.startswith("# TYPE "):
            parts = line.split()
            if len(parts) >= 4:
                types[parts[2]] = parts[3]
            continue
        if line.startswith("#") or not line.strip():
            continue
        m = sample.match(line)
        if not m:
            continue
        d = labels.setdefault(m.group(1), {})
        for mm in re.finditer(r'([a-zA-Z_]\w*)="((?:[^"\\]|\\.)*)"', m.group(3) or ""):
            d.setdefault(mm.group(1), set()).add(mm.group(2))
    return types, labels


def cmd_metrics(scrape: str | None) -> int:
    c = Checker("metrics")
    contract = load_contract()
    c.ok(bool(contract), f"{rel(CONTRACT)} lists {len(contract)} metric families")
    used: dict[str, set[str]] = {}
    problems: list[str] = []
    n_sel = 0
    for where, expr in queries():
        for name, matchers in selectors(expr):
            n_sel += 1
            fam, suffix = resolve(name, contract)
            if fam is None:
                problems.append(f"{where}: unknown metric {name}")
                continue
            used.setdefault(fam, set()).add(name)
            spec = contract[fam]
            allowed = dict(spec["labels"])
            allowed.setdefault("job", None)
            allowed.setdefault("instance", None)
            if suffix == "_bucket":
                allowed["le"] = None
            for label, op, value in matchers:
                if label == "?":
                    problems.append(f"{where}: cannot parse matchers of {name}: {value!r}")
                    continue
                if label not in allowed:
                    problems.append(f"{where}: {name} has no label {label!r} (contract: {sorted(allowed)})")
                    continue
                vals = allowed[label]
                if vals is None:
                    continue
                alts = value.split("|") if op in ("=~", "!~") else [value]
                for alt in alts:
                    if re.fullmatch(r"[A-Za-z0-9_]+", alt) and alt not in vals:
                        problems.append(f"{where}: {name}{{{label}{op}\"{value}\"}}: {alt!r} is not one of {sorted(vals)}")
    c.ok(n_sel > 0, f"found {n_sel} series selectors in dashboard and alert queries")
    c.ok(not problems, "every queried metric, label and label value is in the contract", "\n        " + "\n        ".join(problems))
    unused = sorted(n for n, s in contract.items() if n.startswith("planet_") and n not in used)
    if unused:
        c.warn(f"contract metrics not queried by dashboard or alerts: {', '.join(unused)}")
    else:
        c.ok(True, "every planet_* metric of the contract is shown or alerted on")

    if not scrape:
        c.note("no /metrics scrape given: skipped the check against a live server (deploy/check.sh SCRAPE_FILE)")
        return c.done()
    sp = Path(scrape)
    if not c.ok(sp.is_file(), f"scrape file {scrape} exists"):
        return c.done()
    types, labels = parse_scrape(sp)
    present = set(types) | set(labels)
    for s in list(labels):
        for suf in HIST_SUFFIXES + ("_created",):
            if s.endswith(suf):
                present.add(s[: -len(suf)])
    c.ok(bool(present), f"scrape has {len(present)} series names")
    missing = []
    for fam, names in sorted(used.items()):
        if contract[fam]["type"] == "synthetic":
            continue
        for q in sorted(names):
            base = q
            for suf in HIST_SUFFIXES:
                if q.endswith(suf):
                    base = q[: -len(suf)]
            if q not in present and base not in present:
                missing.append(q)
    c.ok(not missing, "every queried metric name is in the scrape", ", ".join(missing))
    for fam, spec in sorted(contract.items()):
        if spec["type"] == "synthetic" or not fam.startswith("planet_"):
            continue
        if fam in types:
            c.ok(types[fam] == spec["type"], f"{fam} has type {spec['type']}", f"scrape says {types[fam]}")
        elif fam not in present:
            c.warn(f"{fam} not in scrape (a metric with labels appears only once a child was created)")
        samples = [s for s in labels if s == fam or (s.startswith(fam) and s[len(fam):] in HIST_SUFFIXES)]
        for s in samples:
            extra = set(labels[s]) - set(spec["labels"]) - {"le"}
            c.ok(not extra, f"{s} labels are declared", f"undeclared {sorted(extra)}")
            for lab, vals in spec["labels"].items():
                if vals and lab in labels[s] and not labels[s][lab] <= vals:
                    c.warn(f"{s}: {lab} values {sorted(labels[s][lab] - vals)} not in the contract")
    undeclared = sorted(f for f in types if f.startswith("planet_") and f not in contract)
    if undeclared:
        c.warn(f"scrape has planet_* metrics not in the contract: {', '.join(undeclared)}")
    return c.done()


# --------------------------------------------------------------------------
# server.toml and the ConfigMap copy


def check_server_config(c: Checker, cfg: dict, where: str) -> None:
    for k in ("listen", "metrics", "cert", "key", "max_connections", "idle_timeout_ms"):
        c.ok(k in cfg, f"{where}: has {k}")
    dbs = cfg.get("database", [])
    c.ok(isinstance(dbs, list) and len(dbs) > 0 and all("name" in d and "path" in d for d in dbs),
         f"{where}: [[database]] entries have name and path")
    names = {d.get("name") for d in dbs}
    tenants = cfg.get("tenant", [])
    c.ok(isinstance(tenants, list) and len(tenants) > 0, f"{where}: has [[tenant]] entries")
    for t in tenants:
        tn = t.get("name", "?")
        c.ok(("token" in t) != ("token_file" in t), f"{where}: tenant {tn} has exactly one of token / token_file")
        c.ok(set(t.get("databases", [])) <= names and bool(t.get("databases")),
             f"{where}: tenant {tn} databases are declared", str(t.get("databases")))
        for k in ("max_in_flight", "max_bytes_per_second"):
            c.ok(isinstance(t.get(k), int) and t.get(k) >= 0, f"{where}: tenant {tn} {k} is a non-negative integer")


def alert_max_connections() -> int | None:
    for g in load_yaml_docs(ALERTS)[0].get("groups", []):
        for r in g.get("rules", []):
            if r.get("alert") == "PlanetServerConnectionsNearMax":
                m = re.search(r"planet_connections_active\)?\s*/\s*(\d+)", r["expr"])
                return int(m.group(1)) if m else None
    return None


def k8s_objects() -> dict[tuple[str, str], dict]:
    objs = {}
    for f in sorted(K8S.glob("*.yaml")):
        if f.name == "kustomization.yaml":
            continue
        for d in load_yaml_docs(f):
            objs[(d["kind"], d["metadata"]["name"])] = d
    return objs


def cmd_config() -> int:
    c = Checker("config")
    path = DEPLOY / "server.toml"
    try:
        cfg = tomllib.loads(path.read_text())
        c.ok(True, f"{rel(path)} parses as TOML")
        check_server_config(c, cfg, rel(path))
    except Exception as e:  # noqa: BLE001
        c.ok(False, f"{rel(path)} parses as TOML", str(e))
        cfg = {}
    objs = k8s_objects()
    cm = objs.get(("ConfigMap", "planet-server-config"))
    if not c.ok(cm is not None and "server.toml" in cm.get("data", {}), "k8s ConfigMap planet-server-config has server.toml"):
        return c.done()
    try:
        kcfg = tomllib.loads(cm["data"]["server.toml"])
        c.ok(True, "k8s server.toml parses as TOML")
        check_server_config(c, kcfg, "k8s server.toml")
    except Exception as e:  # noqa: BLE001
        c.ok(False, "k8s server.toml parses as TOML", str(e))
        return c.done()
    amax = alert_max_connections()
    for where, conf in (("server.toml", cfg), ("k8s server.toml", kcfg)):
        if conf:
            c.ok(amax == conf.get("max_connections"), f"{where}: max_connections matches the saturation alert ({amax})",
                 str(conf.get("max_connections")))

    # Every path the k8s config names is provided by the Deployment.
    dep = objs[("Deployment", "planet-server")]
    pod = dep["spec"]["template"]["spec"]
    ctr = pod["containers"][0]
    vols = {v["name"]: v for v in pod.get("volumes", [])}
    provided: set[str] = set()
    mount_dirs: dict[str, dict] = {}
    for m in ctr.get("volumeMounts", []):
        v = vols.get(m["name"], {})
        mount_dirs[m["mountPath"]] = v
        for src in v.get("projected", {}).get("sources", []):
            for kind in ("configMap", "secret"):
                if kind in src:
                    ref = objs.get(("ConfigMap" if kind == "configMap" else "Secret", src[kind]["name"]))
                    keys = set((ref or {}).get("data", {}) or {}) | set((ref or {}).get("stringData", {}) or {})
                    for it in src[kind].get("items", []):
                        c.ok(it["key"] in keys, f"projected {kind} {src[kind]['name']} has key {it['key']}")
                        provided.add(m["mountPath"].rstrip("/") + "/" + it["path"])
    cmdline = ctr.get("command", []) + ctr.get("args", [])
    conf_path = cmdline[cmdline.index("--config") + 1] if "--config" in cmdline else None
    c.ok(conf_path in provided, f"Deployment provides the config file {conf_path}")
    for k in ("cert", "key"):
        c.ok(kcfg.get(k) in provided, f"Deployment provides {k} {kcfg.get(k)}")
    for t in kcfg.get("tenant", []):
        if "token_file" in t:
            c.ok(t["token_file"] in provided, f"Deployment provides token_file {t['token_file']}")
    for d in kcfg.get("database", []):
        under = [mp for mp in mount_dirs if d["path"].startswith(mp.rstrip("/") + "/")]
        c.ok(bool(under) and "persistentVolumeClaim" in mount_dirs[under[0]],
             f"database {d['name']} ({d['path']}) is on the database volume")
    port = lambda a: int(a.rsplit(":", 1)[1])  # noqa: E731
    cports = {p["name"]: p for p in ctr.get("ports", [])}
    c.ok(cports.get("quic", {}).get("containerPort") == port(kcfg["listen"]) and cports["quic"].get("protocol") == "UDP",
         "container port quic (UDP) matches listen")
    c.ok(cports.get("metrics", {}).get("containerPort") == port(kcfg["metrics"]), "container port metrics matches metrics")
    return c.done()


# --------------------------------------------------------------------------
# Kubernetes cross-references (schemas are checked by kubernetes-validate)


def cmd_k8s() -> int:
    c = Checker("k8s")
    kust = load_yaml_docs(K8S / "kustomization.yaml")[0]
    res = kust.get("resources", [])
    files = sorted(f.name for f in K8S.glob("*.yaml") if f.name != "kustomization.yaml")
    c.ok(sorted(res) == files, "kustomization.yaml lists every manifest", f"{sorted(res)} vs {files}")
    c.ok("namespace" not in kust and all("namespace" not in d.get("metadata", {})
                                         for f in files for d in load_yaml_docs(K8S / f)),
         "manifests are namespace-free")
    objs = k8s_objects()
    for kind, name in [("Deployment", "planet-server"), ("Service", "planet-server"), ("Service", "planet-server-metrics"),
                       ("ConfigMap", "planet-server-config"), ("Secret", "planet-server-tokens"),
                       ("Secret", "planet-server-tls"), ("PersistentVolumeClaim", "planet-databases"),
                       ("HorizontalPodAutoscaler", "planet-server"), ("PodDisruptionBudget", "planet-server")]:
        c.ok((kind, name) in objs, f"{kind}/{name} defined")
    if c.failed:
        return c.done()
    dep = objs[("Deployment", "planet-server")]
    pod = dep["spec"]["template"]["spec"]
    ctr = pod["containers"][0]
    labels = dep["spec"]["template"]["metadata"]["labels"]
    sel = dep["spec"]["selector"]["matchLabels"]
    c.ok(dep["spec"].get("replicas") == 3, "Deployment has 3 replicas")
    c.ok(sel.items() <= labels.items(), "Deployment selector matches its pod labels")
    rp, lp = ctr.get("readinessProbe", {}).get("httpGet", {}), ctr.get("livenessProbe", {}).get("httpGet", {})
    c.ok(rp.get("path") == "/readyz" and rp.get("port") in ("metrics", 9100), "readiness probe GET /readyz on 9100")
    c.ok(lp.get("path") == "/healthz" and lp.get("port") in ("metrics", 9100), "liveness probe GET /healthz on 9100")
    sc = {**pod.get("securityContext", {}), **ctr.get("securityContext", {})}
    c.ok(sc.get("runAsNonRoot") is True and sc.get("runAsUser") == 10001, "runs as non-root uid 10001")
    c.ok(sc.get("readOnlyRootFilesystem") is True, "read-only root filesystem")
    c.ok(bool(ctr.get("resources", {}).get("requests")), "resource requests set (placeholder)")
    c.ok(all(m.get("readOnly") for m in ctr["volumeMounts"] if m["mountPath"] in ("/data", "/etc/planet")),
         "/data and /etc/planet mounted read-only")
    pvc = objs[("PersistentVolumeClaim", "planet-databases")]
    c.ok(pvc["spec"]["accessModes"] == ["ReadOnlyMany"], "database PVC is ReadOnlyMany")
    svc = objs[("Service", "planet-server")]
    c.ok(svc["spec"]["type"] == "LoadBalancer" and any(p["protocol"] == "UDP" and p["port"] == 4433 for p in svc["spec"]["ports"]),
         "Service planet-server is a UDP 4433 LoadBalancer")
    msvc = objs[("Service", "planet-server-metrics")]
    c.ok(msvc["spec"].get("type", "ClusterIP") == "ClusterIP" and any(p["port"] == 9100 for p in msvc["spec"]["ports"]),
         "Service planet-server-metrics is ClusterIP 9100")
    for s in (svc, msvc):
        c.ok(s["spec"]["selector"].items() <= labels.items(), f"Service {s['metadata']['name']} selects the pods")
        cports = {p["name"] for p in ctr["ports"]}
        c.ok(all(p.get("targetPort") in cports | {p["port"]} for p in s["spec"]["ports"]),
             f"Service {s['metadata']['name']} targets named container ports")
    hpa = objs[("HorizontalPodAutoscaler", "planet-server")]
    c.ok(hpa["apiVersion"] == "autoscaling/v2" and hpa["spec"]["scaleTargetRef"]["name"] == "planet-server"
         and any(m.get("resource", {}).get("name") == "cpu" for m in hpa["spec"]["metrics"]),
         "HPA autoscaling/v2 on CPU targets the Deployment")
    c.ok(hpa["spec"].get("minReplicas", 1) >= 3, "HPA keeps at least 3 replicas")
    pdb = objs[("PodDisruptionBudget", "planet-server")]
    c.ok(pdb["spec"]["selector"]["matchLabels"].items() <= labels.items(), "PDB selects the pods")
    for name in ("planet-server-tokens", "planet-server-tls"):
        s = objs[("Secret", name)]
        vals = " ".join(str(v) for v in (s.get("stringData") or {}).values())
        if "REPLACE_ME" in vals:
            c.note(f"Secret/{name} holds REPLACE_ME placeholders (replace before applying)")
    return c.done()


# --------------------------------------------------------------------------
# The image, the Kubernetes manifests and the compose file agree (driven by
# deploy/container-test.sh with the built image and measured figures)

# The server's longest drain on SIGTERM: shutdown_grace (10 s, in-flight
# responses), +3 s for connection tasks, +2 s for the endpoint to go idle
# (server/src/lib.rs, Server::shutdown and the accept loop).
SERVER_MAX_DRAIN_S = 15
# Memory per connection measured by `planet-bench load` with 1000 clients
# (docs/BENCHMARKS.md, "Load (planet-bench load)": 54 KiB anonymous idle,
# 82 KiB at peak load), in KiB: the peak figure.
DOCUMENTED_KIB_PER_CONNECTION = 82


def deployment_container() -> tuple[dict, dict]:
    dep = k8s_objects()[("Deployment", "planet-server")]
    pod = dep["spec"]["template"]["spec"]
    return pod, pod["containers"][0]


def probe_list() -> list[tuple[str, str, str]]:
    _, ctr = deployment_container()
    out = []
    for kind in ("readiness", "liveness", "startup"):
        g = ctr.get(f"{kind}Probe", {}).get("httpGet", {})
        if g:
            out.append((kind, g["path"], str(g["port"])))
    return out


def grace_seconds() -> int:
    """The shortest grace period the manifests give (k8s, compose)."""
    pod, _ = deployment_container()
    compose = load_yaml_docs(DEPLOY / "compose.yaml")[0]["services"]["planet-server"]
    return min(int(pod["terminationGracePeriodSeconds"]), duration_s(compose.get("stop_grace_period", "10s")))


def duration_s(d: str | int) -> int:
    m = re.fullmatch(r"(?:(\d+)m)?(?:(\d+)s)?", str(d))
    if isinstance(d, int) or not m or not any(m.groups()):
        return int(d)
    return int(m.group(1) or 0) * 60 + int(m.group(2) or 0)


def mebibytes(q: str) -> float:
    units = {"Ki": 1 / 1024, "Mi": 1, "Gi": 1024, "Ti": 1024 * 1024, "K": 1e3 / 2**20, "M": 1e6 / 2**20, "G": 1e9 / 2**20}
    m = re.fullmatch(r"(\d+(?:\.\d+)?)([KMGT]i?)?", q)
    if not m:
        raise ValueError(f"memory quantity {q!r}")
    return float(m.group(1)) * (units[m.group(2)] if m.group(2) else 1 / 2**20)


def cmd_agree(image_json: str, kib_per_conn: float, drain_ms: float) -> int:
    c = Checker("agree")
    img = json.loads(Path(image_json).read_text())[0]
    cfg = img.get("Config", {})
    pod, ctr = deployment_container()
    compose = load_yaml_docs(DEPLOY / "compose.yaml")[0]["services"]["planet-server"]
    sc = {**pod.get("securityContext", {}), **ctr.get("securityContext", {})}
    kcfg = tomllib.loads(k8s_objects()[("ConfigMap", "planet-server-config")]["data"]["server.toml"])
    scfg = tomllib.loads((DEPLOY / "server.toml").read_text())

    # image name
    repo = lambda ref: ref.rsplit("/", 1)[-1].split(":")[0].split("@")[0]  # noqa: E731
    names = {"image": repo(img.get("RepoTags", ["?"])[0]), "k8s": repo(ctr["image"]), "compose": repo(compose["image"])}
    c.ok(len(set(names.values())) == 1, f"image repository name is {names['k8s']} everywhere", str(names))
    # user
    user = f"{sc.get('runAsUser')}:{sc.get('runAsGroup')}"
    c.ok(cfg.get("User") == user == compose.get("user"),
         f"user {user}: image USER, k8s runAsUser/runAsGroup, compose user",
         f"image {cfg.get('User')}, k8s {user}, compose {compose.get('user')}")
    # ports
    img_ports = set(cfg.get("ExposedPorts", {}))
    k8s_ports = {f"{p['containerPort']}/{p.get('protocol', 'TCP').lower()}" for p in ctr["ports"]}
    comp_ports = {re.sub(r"^.*:", "", str(p)) for p in compose.get("ports", [])}
    comp_ports = {p if "/" in p else p + "/tcp" for p in comp_ports}
    port = lambda a: a.rsplit(":", 1)[1]  # noqa: E731
    conf_ports = {f"{port(kcfg['listen'])}/udp", f"{port(kcfg['metrics'])}/tcp"}
    sconf_ports = {f"{port(scfg['listen'])}/udp", f"{port(scfg['metrics'])}/tcp"}
    c.ok(img_ports == k8s_ports == comp_ports == conf_ports == sconf_ports,
         f"ports {sorted(img_ports)}: image EXPOSE, k8s containerPorts, compose ports, both server.toml",
         f"k8s {sorted(k8s_ports)}, compose {sorted(comp_ports)}, configmap {sorted(conf_ports)}, server.toml {sorted(sconf_ports)}")
    # probes and HEALTHCHECK
    hc = " ".join((img.get("Healthcheck") or cfg.get("Healthcheck") or {}).get("Test", []))
    m = re.search(r"http://127\.0\.0\.1:(\d+)(/\S*)", hc)
    probes = {k: (path, p) for k, path, p in probe_list()}
    metrics_port = port(kcfg["metrics"])
    named = {p["name"]: str(p["containerPort"]) for p in ctr["ports"]}
    c.ok(bool(m) and m.group(1) == metrics_port and (m.group(2), metrics_port) in
         {(path, named.get(p, p)) for k, (path, p) in probes.items() if k != "readiness"},
         "image HEALTHCHECK URL is the liveness/startup probe's path and port", f"{hc} vs {probes}")
    c.ok(probes.get("readiness", ("", ""))[0] == "/readyz" and named.get(probes["readiness"][1], probes["readiness"][1]) == metrics_port,
         "readiness probe GET /readyz on the metrics port")
    # command
    cmd = cfg.get("Cmd") or []
    c.ok(ctr.get("command", [])[: len(cmd)] == cmd and compose.get("command", [])[: len(cmd)] == cmd
         and ctr.get("command") == compose.get("command"),
         "k8s and compose run the image's CMD with the same arguments", f"{cmd} / {ctr.get('command')} / {compose.get('command')}")
    # mounts
    vols = set(cfg.get("Volumes") or {})
    k8s_mounts = {m["mountPath"]: bool(m.get("readOnly")) for m in ctr.get("volumeMounts", [])}
    comp = {t: ro for _, t, ro in bind_mounts(compose)}
    for v in sorted(vols):
        c.ok(k8s_mounts.get(v) is True, f"k8s mounts image volume {v} read-only")
        c.ok(any(t == v or t.startswith(v + "/") for t in comp) and all(ro for t, ro in comp.items() if t.startswith(v)),
             f"compose mounts image volume {v} (or files under it) read-only")
    c.ok(sc.get("readOnlyRootFilesystem") is True and compose.get("read_only") is True,
         "read-only root filesystem in k8s and compose (the test ran with --read-only)")
    c.ok("/tmp" in k8s_mounts and "/tmp" in (compose.get("tmpfs") or []), "a writable /tmp in k8s (emptyDir) and compose (tmpfs)")
    # grace period
    k8s_grace = int(pod["terminationGracePeriodSeconds"])
    comp_grace = duration_s(compose.get("stop_grace_period", "10s"))
    c.ok(min(k8s_grace, comp_grace) > SERVER_MAX_DRAIN_S,
         f"grace periods (k8s {k8s_grace} s, compose {comp_grace} s) exceed the server's longest drain ({SERVER_MAX_DRAIN_S} s)")
    c.ok(drain_ms / 1000 < min(k8s_grace, comp_grace), f"measured drain {drain_ms / 1000:.2f} s is within both grace periods")
    # resources from memory per connection: the documented figure (1000
    # clients) sizes them; the container's own (a few dozen clients, whole
    # RSS sampled each second) is printed beside it, too noisy to assert on.
    kib = DOCUMENTED_KIB_PER_CONNECTION
    max_conn = int(kcfg["max_connections"])
    need = max_conn * kib / 1024
    req = mebibytes(ctr["resources"]["requests"]["memory"])
    lim = mebibytes(ctr["resources"]["limits"]["memory"])
    c.ok(req >= need and lim >= 2 * need,
         f"memory request {req:.0f} MiB >= max_connections {max_conn} x {kib} KiB (docs/BENCHMARKS.md, Load) = {need:.0f} MiB, "
         f"limit {lim:.0f} MiB >= twice that")
    c.note(f"memory per connection in the container test: {kib_per_conn:.1f} KiB (RSS, few clients: a cross-check only)")
    return c.done()


def main(argv: list[str]) -> int:
    if not argv:
        print(__doc__)
        return 2
    cmd, args = argv[0], argv[1:]
    if cmd == "dockerfile":
        return cmd_dockerfile()
    if cmd == "compose":
        return cmd_compose()
    if cmd == "grafana":
        return cmd_grafana()
    if cmd == "config":
        return cmd_config()
    if cmd == "k8s":
        return cmd_k8s()
    if cmd == "promql-rules":
        return cmd_promql_rules(args[0])
    if cmd == "metrics":
        return cmd_metrics(args[0] if args else None)
    if cmd == "probes":
        for kind, path, port in probe_list():
            print(kind, path, port)
        return 0
    if cmd == "grace":
        print(grace_seconds())
        return 0
    if cmd == "agree" and len(args) == 3:
        return cmd_agree(args[0], float(args[1]), float(args[2]))
    print(f"unknown subcommand {cmd}\n{__doc__}")
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
