"""Structural checks of deploy/ that no schema covers: what the issue and the README promise of
the Compose file, the Dockerfile and the kustomization, and that every TESSERA_* variable the
files set is one the binary reads (when the binary is given)."""

import pathlib
import re
import subprocess
import sys

import yaml

here = pathlib.Path(sys.argv[1])
tessera = sys.argv[2] if len(sys.argv) > 2 else ""
failures = []


def check(ok, what):
    if not ok:
        failures.append(what)


def http_port(args):
    """The port of the coordinator's --http address in a command line, or "" without one."""
    return args[args.index("--http") + 1].rpartition(":")[2] if "--http" in args else ""


# Kustomization: every resource exists; every manifest is listed (hpa.yaml optional).
kust = yaml.safe_load((here / "k8s/kustomization.yaml").read_text())
listed = set(kust.get("resources", []))
for r in listed:
    check((here / "k8s" / r).exists(), f"kustomization lists {r}, which does not exist")
for f in (here / "k8s").glob("*.yaml"):
    if f.name not in ("kustomization.yaml", "hpa.yaml"):
        check(f.name in listed, f"k8s/{f.name} is not in kustomization.yaml")
docs = [d for f in (here / "k8s").glob("*.yaml") if f.name != "kustomization.yaml"
        for d in yaml.safe_load_all(f.read_text()) if d]
kinds = {(d["kind"], d["metadata"]["name"]) for d in docs}
for want in [("StatefulSet", "tessera-coordinator"), ("Service", "tessera-coordinator"),
             ("Deployment", "tessera-worker"), ("Secret", "tessera-token"),
             ("HorizontalPodAutoscaler", "tessera-worker")]:
    check(want in kinds, f"k8s: no {want[0]} {want[1]}")
for d in docs:
    if d["kind"] in ("StatefulSet", "Deployment"):
        pod = d["spec"]["template"]["spec"]
        check(pod.get("securityContext", {}).get("runAsNonRoot") is True, f"{d['metadata']['name']}: not runAsNonRoot")
        for c in pod["containers"]:
            for probe in ("readinessProbe", "livenessProbe"):
                check(probe in c, f"{d['metadata']['name']}: no {probe}")
            check("limits" in c.get("resources", {}), f"{d['metadata']['name']}: no resource limits")
    if d["kind"] == "StatefulSet":
        check(d["spec"].get("volumeClaimTemplates"), "coordinator: no PersistentVolumeClaim template")
        # The dashboard: served (--http) on the port the container and the Service name "http".
        c = d["spec"]["template"]["spec"]["containers"][0]
        ports = {p["name"]: p["containerPort"] for p in c.get("ports", [])}
        check(http_port(c.get("args", [])) == str(ports.get("http")), "coordinator: --http is not the container's port http")
        service = [s for s in docs if (s["kind"], s["metadata"]["name"]) == ("Service", "tessera-coordinator")]
        check(service and any(p.get("targetPort") == "http" for p in service[0]["spec"]["ports"]),
              "coordinator: the Service does not expose the dashboard")

# KEDA (a CRD no schema here covers): a ScaledObject for the worker Deployment that scales to zero
# on the coordinator's queue gauges, which the binary must export.
keda = [d for d in yaml.safe_load_all((here / "k8s/keda/scaledobject.yaml").read_text()) if d]
check(len(keda) == 1, "keda: not one document")
so = keda[0]
check(so.get("apiVersion") == "keda.sh/v1alpha1" and so.get("kind") == "ScaledObject", "keda: not a keda.sh/v1alpha1 ScaledObject")
check(so["metadata"].get("namespace") == "tessera", "keda: not in the tessera namespace")
target = so["spec"]["scaleTargetRef"]
check((target.get("kind"), target.get("name")) == ("Deployment", "tessera-worker") and ("Deployment", "tessera-worker") in kinds,
      "keda: does not scale the worker Deployment")
check(so["spec"].get("minReplicaCount") == 0, "keda: does not scale to zero")
check(isinstance(so["spec"].get("maxReplicaCount"), int) and so["spec"]["maxReplicaCount"] >= 1, "keda: no maxReplicaCount")
allowed = {"scaleTargetRef", "minReplicaCount", "maxReplicaCount", "pollingInterval", "cooldownPeriod", "triggers",
           "idleReplicaCount", "fallback", "advanced", "initialCooldownPeriod"}
check(set(so["spec"]) <= allowed, f"keda: unknown spec fields {set(so['spec']) - allowed}")
for t in so["spec"]["triggers"]:
    check(t.get("type") == "prometheus", "keda: a trigger is not prometheus")
    meta = t.get("metadata", {})
    check(all(isinstance(meta.get(k), str) for k in ("serverAddress", "query", "threshold")), "keda: trigger metadata incomplete")
    # The coordinator's sources, wherever in them the metrics are written (http/metrics.rs today).
    exported = "".join(f.read_text() for f in sorted((here / "../crates/coordinator/src").rglob("*.rs")))
    gauges = re.findall(r"\b(tessera_[a-z_]+)", meta.get("query", ""))
    check(gauges, "keda: the query reads no tessera gauge")
    for gauge in gauges:
        check(f'"{gauge}"' in exported, f"keda: the coordinator exports no {gauge}")

# Compose: a coordinator with a volume, two workers, a one-shot submit of the built-in scene.
compose = yaml.safe_load((here / "compose.yaml").read_text())
services = compose["services"]
check(set(services) >= {"coordinator", "worker", "submit"}, "compose: services missing")
check(any(":/data" in v for v in services["coordinator"].get("volumes", [])), "compose: coordinator has no data volume")
port = http_port(services["coordinator"]["command"])
check(port and any(p.endswith(":" + port) for p in services["coordinator"].get("ports", [])),
      "compose: the coordinator's dashboard (--http) is not published")
check(services["worker"].get("deploy", {}).get("replicas") == 2, "compose: not two workers")
check(services["submit"]["command"][:2] == ["submit", "builtin:cornell-box"], "compose: submit does not submit the built-in scene")
check(services["submit"].get("restart") == "no", "compose: submit is not one-shot")
for name in ("worker", "submit"):
    check(services[name]["depends_on"]["coordinator"]["condition"] == "service_healthy", f"compose: {name} does not wait")

# Dockerfile: multi-stage, non-root, the one binary.
dockerfile = (here / "Dockerfile").read_text()
check(len(re.findall(r"^FROM ", dockerfile, re.M)) >= 2, "Dockerfile: not multi-stage")
users = re.findall(r"^USER (\S+)", dockerfile, re.M)
check(users and not users[-1].startswith(("0", "root")), "Dockerfile: final stage runs as root")
check('ENTRYPOINT ["/usr/local/bin/tessera"]' in dockerfile, "Dockerfile: entrypoint is not the tessera binary")

# Every TESSERA_* variable the files set is read by the binary (script-only ones excepted).
script_only = {"TESSERA_BIN", "TESSERA_SLURM_PORT", "TESSERA_UID", "TESSERA_CHECK_VENV"}
used = set()
for f in here.rglob("*"):
    if f.is_file() and f.name not in ("check", "check.py"):
        used |= set(re.findall(r"\bTESSERA_[A-Z_]+[A-Z]\b", f.read_text(errors="ignore")))
if tessera:
    helps = ""
    for cmd in (["--help"], ["coordinator", "--help"], ["worker", "--help"], ["submit", "--help"], ["status", "--help"]):
        helps += subprocess.run([tessera, *cmd], capture_output=True, text=True, check=True).stdout
    known = set(re.findall(r"env: (TESSERA_[A-Z_]+)", helps))
    for v in sorted(used - script_only):
        check(v in known, f"{v} is set in deploy/ but no command reads it")

if failures:
    print("deploy checks failed:", *failures, sep="\n  ")
    sys.exit(1)
print(f"deploy: kustomization, compose, Dockerfile and {len(used)} variables checked")
