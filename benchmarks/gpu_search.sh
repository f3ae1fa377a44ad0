#!/usr/bin/env bash
# The precision search of config/gpu_search.yaml on the GPU-trained pi0.5 (issue 52), then its confirmation, across
# device calls of at most 9 minutes: benchmarks/gpu_study.sh's carry, resume and deadline with the search's phases.
# One call:
#   run(kind="nvidia-h100-x1", timeout_s=600, carry=[".gpuwork/study-stack", ".carry/gpu_search"],
#       command="OUT=$OUT STUDY_END_S=470 bash benchmarks/gpu_search.sh")
# then, here, with the reply's files_at:  bash benchmarks/gpu_search.sh keep FILES_AT
# Phase 1, config/gpu_search.yaml config/gpu_search_baseline.yaml: the baseline alone (500 episodes in full), the
# whole node to its one job (15 simulator workers; how a cell runs is not hashed: the search's own baseline cell).
# Phase 2, config/gpu_search.yaml: the 30 candidates, three at a time in the search's order (cheapest weight memory
# first: rule rollout's priority), each under the live rule at 0.05 / 30 against the baseline's records. As each
# cell finishes, `search-state` decides the search from the finished candidates' decisions; once they determine it
# (the cheaper candidates decided or at their cap, and a not_worse among them) the rollouts still running are stopped
# (their journals kept) and tables/search_chosen.yaml names the chosen cell study.allocations.gpu_search.
# Phase 3, config/gpu_search.yaml tables/search_chosen.yaml config/gpu_search_confirm.yaml: the chosen allocation and
# full precision on run seed 1, in full, two cells at once (skipped while the search is not determined, or when it
# chose nothing).
# SEARCH_UNTIL= (empty) runs every candidate of phase 2 to its decision instead (the exhaustive comparison).
# Everything else (the stack, what comes back, keep, plan, save, resume, export) is benchmarks/gpu_study.sh's; here
# the carry is .carry/gpu_search, the progress results/gpu_search_progress.tsv, and `save` / `export` write
# results/gpu_search/{live,confirm}/ (each phase's finished cells) and the carry to results/gpu_search/carry/.
# docs/gpu_study.md ("The precision search") gives the whole procedure.
export PHASES=${PHASES:-"config/gpu_search.yaml config/gpu_search_baseline.yaml;config/gpu_search.yaml;config/gpu_search.yaml tables/search_chosen.yaml config/gpu_search_confirm.yaml"}
export EXPORTS=${EXPORTS:-"live;live;confirm"}
export CARRY=${CARRY:-.carry/gpu_search}
export RETURNED=${RETURNED:-.gpuwork/gpu_search/returned}
export SAVED=${SAVED:-results/gpu_search/carry}
export PROGRESS=${PROGRESS:-results/gpu_search_progress.tsv}
export EXPORT_DIR=${EXPORT_DIR:-results/gpu_search}
export SEARCH_UNTIL=${SEARCH_UNTIL-determined}
exec bash "$(dirname "$0")/gpu_study.sh" "$@"
