#!/usr/bin/env bash
# The test suite (creates .venv on first run). CI runs exactly this.
source "$(dirname "$0")/env.sh"
exec python -m pytest tests "$@"
