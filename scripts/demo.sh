#!/usr/bin/env bash
# Main job on the bundled default (creates .venv on first run).
source "$(dirname "$0")/env.sh"
exec python eval/demo.py "$@"
