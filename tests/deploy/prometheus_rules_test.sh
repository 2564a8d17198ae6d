#!/usr/bin/env bash
# The shipped Prometheus rules (deploy/prometheus/sms-gateway-rules.yml): promtool checks them and
# runs their cases (prometheus_rules_test.yml); every alert has a case, and every metric a rule
# reads is one the gateway serves (a row of docs/OPERATIONS.md, which the doc test holds to the
# code), so a renamed metric cannot leave an alert that never fires; OPERATIONS.md lists each alert.
#
#   prometheus_rules_test.sh SOURCE_DIR
set -euo pipefail
source=$1
rules=$source/deploy/prometheus/sms-gateway-rules.yml
cases=$source/tests/deploy/prometheus_rules_test.yml
command -v promtool >/dev/null || { echo "prometheus_rules_test: promtool is missing (apt-get install prometheus)" >&2; exit 1; }
promtool check rules "$rules"
(cd "$(dirname "$cases")" && promtool test rules "$(basename "$cases")")
/usr/bin/python3 - "$rules" "$cases" "$source/docs/OPERATIONS.md" <<'PY'
import re, sys, yaml
rules = yaml.safe_load(open(sys.argv[1]))
cases = yaml.safe_load(open(sys.argv[2]))
operations = open(sys.argv[3], encoding="utf-8").read()
documented = set(re.findall(r"^\| `(sms_gateway_[a-z0-9_]+)`", operations, re.M))
errors = []
alerts = [r["alert"] for g in rules["groups"] for r in g["rules"] if "alert" in r]
tested = {t["alertname"] for case in cases["tests"] for t in case.get("alert_rule_test", [])
          if t.get("exp_alerts")}
errors += [f"alert {a} has no case that fires it in {sys.argv[2]}" for a in alerts if a not in tested]
recorded = {r["record"] for g in rules["groups"] for r in g["rules"] if "record" in r}
for group in rules["groups"]:
    for rule in group["rules"]:
        for metric in re.findall(r"\b(sms_gateway_[a-z0-9_]+)", rule["expr"]):
            if metric not in documented:
                errors.append(f"{rule.get('alert') or rule.get('record')}: reads {metric}, which the gateway does not serve")
        for name in re.findall(r"\b(sms_gateway:[a-z0-9_:]+)", rule["expr"]):
            if name not in recorded:
                errors.append(f"{rule.get('alert') or rule.get('record')}: reads {name}, which no rule records")
errors += [f"docs/OPERATIONS.md: alert {a} is not in the table of \"Alerting\"" for a in alerts
           if f"| `{a}` |" not in operations]
for e in errors:
    print("prometheus_rules_test:", e, file=sys.stderr)
if errors:
    sys.exit(1)
print(f"prometheus_rules_test: {len(alerts)} alerts, each with a firing case; {len(recorded)} recording rules; every metric read is served")
PY
