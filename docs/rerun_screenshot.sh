#!/usr/bin/env bash
# Regenerate docs/images/rerun_view.png: the rerun web viewer showing a demo recording, taken on a headless
# machine by `ar-anchor view --screenshot` (headless Chromium: apt install chromium).
#
# usage: docs/rerun_screenshot.sh [OUT_PNG] [ar-anchor view options, e.g. --frame 60 --layout overlay]
set -euo pipefail

OUT=${1:-"$(cd "$(dirname "$0")" && pwd)/images/rerun_view.png"}
shift || true
WORK=$(mktemp -d /tmp/rerun_shot.XXXXXX)
trap 'rm -rf "$WORK"' EXIT

ar-anchor -q demo --frames 120 --out "$WORK/run"
ar-anchor view "$WORK/run" --screenshot "$OUT" "$@"
