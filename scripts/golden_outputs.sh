#!/usr/bin/env bash
# Write every output a restructure must leave byte-identical, for seven scenarios, into DIR:
# the MCAP of `bttsim simulate`, the summary of `bttsim process`, and the CSV export.
#   scripts/golden_outputs.sh DIR        (then, after a change: scripts/golden_outputs.sh DIR2;
#                                          diff -r DIR DIR2 must print nothing)
set -euo pipefail
out=${1:?usage: scripts/golden_outputs.sh DIR}
repo=$(cd "$(dirname "$0")/.." && pwd)
mkdir -p "$out"
cd "$out"
export OMP_NUM_THREADS=1
cp "$repo/examples/signal_chain.toml" signal_chain.toml
cp "$repo/examples/rotating_stall.toml" stall.toml
cp "$repo/examples/flutter.toml" flutter.toml
printf '' > default.toml
cat > centrifugal.toml <<'EOF'
[model]
centrifugal = true
[speed]
start_rpm = 2300.0
end_rpm = 2900.0
duration_s = 20.0
EOF
cat > mistuned_pad.toml <<'EOF'
[model]
stiffness_std = 0.01
[toa]
method = "PAD"
[speed]
start_rpm = 2300.0
end_rpm = 2900.0
duration_s = 20.0
EOF
cat > from_rest.toml <<'EOF'
[speed]
start_rpm = 2400.0
end_rpm = 2700.0
duration_s = 6.0
initial = "rest"
EOF
for s in default signal_chain stall flutter centrifugal mistuned_pad from_rest; do
  bttsim simulate "$s.toml" --out "$s.mcap" -q > /dev/null 2>&1 || echo "simulate $s failed" >&2
  # process may legitimately find no resonance (exit 0) or say why it cannot (exit 3)
  bttsim process "$s.mcap" --summary "$s.summary.json" > "$s.process.log" 2>&1 || echo "process $s: exit $?" >> "$s.process.log"
  rm -rf "$s.export" && bttsim export "$s.mcap" --format csv --out "$s.export" > /dev/null 2>&1 || echo "export $s failed" >&2
  rm -f "$s.export/run.json.tmp"
done
echo "wrote $(ls "$out" | wc -l) files to $out"
