#!/usr/bin/env bash
# Runs the CRM paper's real-data experiment (`mrfmap experiment crm-laser`, defaults) on each
# CARMEN log given and prints one summary table: the issue's two checks per log (CRM's MAE
# below every log-odds setting of the sweep; CRM's I_c at gamma 2 below the paper ISM's) and
# the numbers behind them. Not part of CI (the logs are not in the repository).
#
# usage: bench/radish.sh [-o DIR] LOG [LOG ...]     (reports in DIR/NAME/, default target/radish)
set -euo pipefail
cd "$(dirname "$0")/.."
out=target/radish
if [[ "${1:-}" == "-o" ]]; then out=$2; shift 2; fi
[[ $# -gt 0 ]] || { echo "usage: bench/radish.sh [-o DIR] LOG [LOG ...]" >&2; exit 1; }
cargo build --release -q -p mrfmap-cli
dirs=()
for log in "$@"; do
  name=$(basename "$log"); name=${name%.gz}; name=${name%.log}; name=${name%.clf}
  target/release/mrfmap -q experiment crm-laser "$log" -o "$out/$name" > /dev/null
  dirs+=("$out/$name")
done
python3 - "${dirs[@]}" <<'PY'
import json, os, sys
print("| log | scans | MAE: CRM 101 / CRM 15 / paper ISM / sweep's best | CRM beats settings | AUC: CRM / paper ISM | I_c (2): CRM / paper ISM | CRM MAE below every setting | CRM I_c below paper ISM |")
print("|---|---|---|---|---|---|---|---|")
for d in sys.argv[1:]:
    v = json.load(open(os.path.join(d, "results.json")))
    crm, crm15, ism = v["methods"]
    best = v["best_of_sweep_by_mae"]
    yes = lambda b: "met" if b else "not met"
    print(f"| {os.path.basename(d)} | {v['scans']} | {crm['mae']:.3f} / {crm15['mae']:.3f} / {ism['mae']:.3f} / {best['mae']:.3f} "
          f"| {v['crm_mae_beats_settings']} of {len(v['sweep'])} | {crm['auc']:.3f} / {ism['auc']:.3f} "
          f"| {crm['ic_2']:.0f} / {ism['ic_2']:.0f} | {yes(v['crm_mae_below_every_setting'])} | {yes(v['crm_ic_2_below_paper_ism'])} |")
PY
