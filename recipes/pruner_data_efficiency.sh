#!/usr/bin/env bash
# The TTS pipeline on N recorded trajectories (the paper's Figs 10-11 shape): the searched steps of
# data_efficiency.sh, plus the step-query pruner trained from them on the same N trajectories.
WITH_PRUNER=1 exec bash "$(dirname "$0")/data_efficiency.sh" "$@"
