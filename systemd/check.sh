#!/bin/sh
# Checks the systemd units: syntax (systemd-analyze verify) and hardening exposure
# (systemd-analyze security --offline=true, threshold 3.0 on systemd's 0..10 scale).
# Usage: systemd/check.sh [threshold]   (by hand; CI's systemd phase, xtask/src/lint.rs, checks
# every unit in systemd/ against its own limit and leaves out the drop-in scored here).
set -eu
here=$(cd "$(dirname "$0")" && pwd)
threshold=${1:-3.0}
command -v systemd-analyze >/dev/null || { echo "check.sh: systemd-analyze not found" >&2; exit 1; }

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT INT TERM
cp "$here/irtrackd.service" "$tmp/"
# verify resolves ExecStart; point it at an existing binary so only our unit is judged.
sed -i "s|^ExecStart=/usr/bin/irtrackd|ExecStart=/bin/true|" "$tmp/irtrackd.service"

echo "== systemd-analyze verify irtrackd.service"
# Anything verify prints fails the check.
out=$(systemd-analyze verify "$tmp/irtrackd.service" 2>&1 || true)
if [ -n "$out" ]; then
    printf '%s\n' "$out" >&2
    echo "check.sh: systemd-analyze verify reported problems" >&2
    exit 1
fi
echo "ok"

# systemd takes the threshold on its internal 0..100 scale (exposure 3.0 -> 30).
t100=$(awk -v t="$threshold" 'BEGIN { printf "%d", t * 10 + 0.5 }')
echo "== systemd-analyze security --offline=true --threshold=$t100 irtrackd.service (exposure <= $threshold)"
if ! out=$(systemd-analyze security --offline=true --threshold="$t100" --no-pager "$tmp/irtrackd.service" 2>&1); then
    printf '%s\n' "$out" >&2
    echo "check.sh: exposure above $threshold" >&2
    exit 1
fi
printf '%s\n' "$out" | grep -e '^✗' -e 'Overall exposure' || true

echo "== with drop-in irtrackd-realtime.conf (informational exposure)"
# A unit may repeat [Service]; appending the drop-in is what systemd's merge amounts to here.
mkdir -p "$tmp/rt"
cat "$tmp/irtrackd.service" "$here/irtrackd-realtime.conf" > "$tmp/rt/irtrackd.service"
out=$(systemd-analyze verify "$tmp/rt/irtrackd.service" 2>&1 || true)
[ -z "$out" ] || { printf '%s\n' "$out" >&2; echo "check.sh: drop-in does not verify" >&2; exit 1; }
systemd-analyze security --offline=true --no-pager "$tmp/rt/irtrackd.service" 2>&1 | grep 'Overall exposure' || true
echo "ok"
