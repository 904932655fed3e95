#!/usr/bin/env bash
# Mutation testing of the core modules with mutmut (PyPI), each module against the tests that
# cover it. Not run in CI: it is CPU-heavy (every mutant re-runs its covering tests).
#
#   scripts/mutation.sh                  # every core module (hours on a 2-core machine)
#   scripts/mutation.sh pose response    # only these (names below)
#   JOBS=1 scripts/mutation.sh pose      # mutmut workers (default 2)
#   SAMPLE=150 scripts/mutation.sh pose  # a fresh run of only a random 150 of the mutants (an
#                                        # estimate; the same draw each time for the same mutants)
#   RECHECK=1 scripts/mutation.sh pose   # after changing code or tests: bring both into the
#                                        # scratch copy and re-run the last run's survivors, and
#                                        # the mutants unchecked (new, or left by an interrupted run)
#   RECHECK=1 SAMPLE=300 ...             # ... only a random 300 of those unchecked (an estimate)
#
# Needs: pip install mutmut (the dev extra). Each module runs in its own scratch copy of the
# repository under ${MUTATION_DIR:-/tmp/neural-collider-mutation}/NAME (mutmut writes its mutants/
# folder there; the shared meshes are linked in), so the working tree is never touched.
# Per module it prints killed / timeout / survived / untested / not checked and the score, and
# writes the surviving and untested mutants' diffs to NAME/survivors.txt. Read the survivors: each is a change no test notices.
set -euo pipefail

ROOT="$(cd "$(dirname "$0")/.." && pwd)"
WORK="${MUTATION_DIR:-/tmp/neural-collider-mutation}"
JOBS="${JOBS:-2}"

# name | files to mutate (under server/ or client/, space-separated globs) | tests that cover them
SIM=client/collider_client/sim
MODULES=(
  "contract|client/collider_contract/*|tests/contract"
  "collider|server/collider_server/engine/collider.py|tests/engine/test_collider.py tests/engine/test_only_colliding.py tests/engine/test_modelfile.py tests/hard_cases/test_engine_hard_cases.py tests/client/test_backends.py tests/engine/kinds/test_skinned.py"
  "kinds|server/collider_server/engine/kinds/*|tests/engine/kinds tests/engine/test_modelfile.py tests/engine/test_analytic.py tests/engine/test_only_colliding.py tests/hard_cases/test_engine_hard_cases.py tests/engine/test_real_meshes.py"
  "batching|server/collider_server/service/batching.py|tests/service/test_batching.py"
  "response|client/collider_client/response.py client/collider_client/physics.py client/collider_client/placement.py|tests/client/test_response.py tests/client/test_newton_adapter.py tests/hard_cases/test_simulator_hard_cases.py"
  "sim|$SIM/cloth.py $SIM/output.py $SIM/run.py $SIM/scene.py $SIM/simulator.py|tests/hard_cases/test_simulator_hard_cases.py tests/client/test_scene.py tests/client/test_simulator.py"
  # The browser views (viser): their pages are built on a real viser server and driven through
  # their controls' callbacks in process; the page itself is also checked in a real browser
  # (tests/views/test_browser.py, which mutmut cannot see).
  "views|server/collider_cli/views/*|tests/views/test_view_parts.py tests/views/test_page.py tests/views/test_collider_page.py tests/views/test_cloth_page.py tests/views/test_animated_page.py tests/views/test_skinned_page.py"
)
#: The packages, each under server/ or client/, that a scratch copy imports from src/.
PACKAGES=(client/collider_contract client/collider_client server/collider_server server/collider_cli)

write_config() {  # the mutmut section of NAME's setup.cfg: files to mutate, tests to run
  local target=$1 tests=$2
  echo "[mutmut]"
  echo "source_paths = src"
  echo "only_mutate ="
  for t in $target; do echo "    src/${t#*/}"; done
  echo "pytest_add_cli_args_test_selection ="
  for t in $tests; do echo "    $t"; done
  echo "pytest_add_cli_args ="
  printf '    %s\n' -p no:cacheprovider -p mutation_one_thread -m "not slow"
  # A mutant whose tests run 3x longer than unmutated ones (plus 10 s) is a timeout (a kill):
  # mutmut's default of 15x lets a mutant that makes chunks tiny run for many minutes.
  printf '%s\n' "timeout_multiplier = 3" "timeout_constant = 10"
  # Help and description texts of CLI options are documentation, not behaviour: not mutated
  # (their first line; the tests check that help states each option's real default).
  printf '%s\n' "do_not_mutate_patterns =" "    \\b(help|description)="
  # The tests read the shipped models and the examples (their meshes, animations, scripts).
  echo "also_copy ="
  printf '    %s\n' models examples mutation_one_thread.py
}

make_scratch_copy() {
  local dir=$1
  rm -rf "$dir" && mkdir -p "$dir"
  # A scratch copy of the tracked files (models included), and the shared meshes beside it
  # where tests/conftest.py looks for them (../shared/data/meshes from the repository root).
  git -C "$ROOT" ls-files -z | (cd "$ROOT" && xargs -0 cp --parents -t "$dir")
  ln -s "$(cd "$ROOT/.." && pwd)/shared" "$dir/shared"
  # mutmut imports the mutated code from mutants/src and names modules by their path under it:
  # put every package there (they import each other).
  mkdir "$dir/src"
  for package in "${PACKAGES[@]}"; do mv "$dir/$package" "$dir/src/"; done
  # mutmut runs the tests once in its own process, then forks a worker per mutant; a child
  # forked after torch has started its OpenMP pool deadlocks in it, and numba's OpenMP layer
  # kills such a child (SIGTERM). Keep torch on one thread and numba on its workqueue layer.
  printf '%s\n' '"""Loaded by scripts/mutation.sh only: torch on one thread, fork-safe."""' \
    'import torch' 'torch.set_num_threads(1)' 'torch.set_num_threads = lambda threads: None' \
    > "$dir/mutation_one_thread.py"
}

with_status() {  # the mutants of results.txt with one of the statuses given, one name per line
  local pattern
  pattern=$(IFS="|"; echo "$*")
  { grep -E ": ($pattern)$" results.txt || true; } | sed -E "s/^ *//; s/: ($pattern)$//"  # none: no lines
}

survivors() { with_status survived "no tests"; }

summarise() {
  local name=$1
  mutmut results --all true > results.txt 2>&1 || true
  count() { grep -c ": $1\$" results.txt || true; }
  local killed timeout survived untested suspicious score
  killed=$(count killed); timeout=$(count timeout); survived=$(count survived)
  untested=$(count "no tests"); suspicious=$(count suspicious); unchecked=$(count "not checked")
  # mutmut's convention: a timeout is a kill. A mutant no test runs is a survivor.
  score=$(python3 -c "k,s=$killed+$timeout,$survived+$untested; print(f'{100*k/max(k+s,1):.1f} %')")
  echo "$name: killed $killed, timeout $timeout, survived $survived, no tests $untested," \
       "suspicious $suspicious, not checked $unchecked; score $score (killed + timeout over" \
       "those + survived + no tests)"
  : > survivors.txt
  for m in $(survivors); do mutmut show "$m" >> survivors.txt 2>&1 || true; done
}

run_list() {  # last run's survivors (none in a fresh run), then the unchecked (SAMPLE: a random N)
  survivors
  # A fixed random source: the same mutants give the same sample, so a figure can be reproduced.
  with_status "not checked" | shuf --random-source=<(yes) | head -n "${SAMPLE:--0}"
}

run_module() {
  local name=$1 target=$2 tests=$3
  local dir="$WORK/$name"
  if [ -n "${RECHECK:-}" ]; then
    [ -f "$dir/setup.cfg" ] || { echo "$name: no earlier run in $dir to recheck" >&2; exit 2; }
    # Today's code and tests into the scratch copy: mutmut keeps the verdicts of functions that
    # did not change and makes new mutants of those that did. The test files stay those of the
    # first run (a new selection resets every verdict): a new file in the list needs a fresh run.
    rm -rf "$dir/tests"
    cp -r "$ROOT/tests" "$dir/tests"
    for package in "${PACKAGES[@]}"; do
      rm -rf "$dir/src/${package#*/}"
      cp -r "$ROOT/$package" "$dir/src/"
    done
  else
    make_scratch_copy "$dir"
    write_config "$target" "$tests" > "$dir/setup.cfg"
    echo "== $name: mutating $target against: $tests"
  fi
  (
    cd "$dir"
    unset PYTHONPATH
    export OMP_NUM_THREADS=1 NUMBA_NUM_THREADS=1 NUMBA_THREADING_LAYER=workqueue PYTHONPATH=.
    if [ -n "${RECHECK:-}" ] || [ -n "${SAMPLE:-}" ]; then
      # A first invocation makes the (new) mutants and collects the (new) tests' stats, then
      # stops (no mutant has that name): mutants run in the invocation that collects the stats
      # were seen to miss the new tests. Then only the chosen mutants run.
      mutmut run --max-children 1 collect-stats-only > run.log 2>&1 || true
      mutmut results --all true > results.txt 2>&1 || true
      local only=() survived unchecked
      survived=$(survivors | wc -l); unchecked=$(with_status "not checked" | wc -l)
      mapfile -t only < <(run_list)
      echo "== $name: running $survived survivors and $((${#only[@]} - survived)) of" \
           "$unchecked unchecked mutants"
      if [ ${#only[@]} -gt 0 ]; then
        mutmut run --max-children "$JOBS" "${only[@]}" >> run.log 2>&1 || true
      fi
    else
      mutmut run --max-children "$JOBS" > run.log 2>&1 || true
    fi
    summarise "$name"
  )
}

# The modules named on the command line, in that order; none: all of them.
names=("$@")
if [ ${#names[@]} -eq 0 ]; then
  for entry in "${MODULES[@]}"; do names+=("${entry%%|*}"); done
fi
for wanted in "${names[@]}"; do
  found=""
  for entry in "${MODULES[@]}"; do
    IFS="|" read -r name target tests <<< "$entry"
    if [ "$name" = "$wanted" ]; then found=1; run_module "$name" "$target" "$tests"; fi
  done
  [ -n "$found" ] || { echo "unknown module $wanted (known: ${MODULES[*]%%|*})" >&2; exit 2; }
done
