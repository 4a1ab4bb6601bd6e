#!/usr/bin/env bash
# Runs the whole DVC pipeline. With a CUDA GPU: the paper profile (params.yaml default).
# Without one: the reduced `ci` profile, said out loud. Override with PROFILE=paper|ci.
set -euo pipefail
cd "$(dirname "$0")/.."
. .venv/bin/activate
export DVC_NO_ANALYTICS=1 HF_HUB_OFFLINE=1
if [ -z "${PROFILE:-}" ]; then
  if python -c "import torch, sys; sys.exit(0 if torch.cuda.is_available() else 1)"; then PROFILE=paper
  else PROFILE=ci; echo "pipeline: no CUDA GPU found: running the reduced 'ci' profile (PROFILE=paper to force full scale)"; fi
fi
# dvc exp run needs a git identity; use a local one when none is configured
git config user.email >/dev/null || export GIT_AUTHOR_NAME=gca GIT_AUTHOR_EMAIL=gca@localhost GIT_COMMITTER_NAME=gca GIT_COMMITTER_EMAIL=gca@localhost
# dvc exp run detaches HEAD while it runs and re-attaches it at the end; if it is interrupted (Ctrl-C, a
# killed job) HEAD stays detached and later commits miss the branch. Re-attach it on any exit.
branch=$(git symbolic-ref -q HEAD || true)
start=$(git rev-parse -q --verify HEAD || true)
reattach() {
  if [ -n "$branch" ] && ! git symbolic-ref -q HEAD >/dev/null \
     && [ "$(git rev-parse -q --verify HEAD)" = "$start" ] && [ "$(git rev-parse -q --verify "$branch")" = "$start" ]; then
    git symbolic-ref HEAD "$branch"
    echo "pipeline: HEAD was left detached by an interrupted dvc exp run: re-attached to ${branch#refs/heads/}" >&2
  fi
}
# dvc exp run -S profile=... writes the override into params.yaml in the working tree: the user's next
# commit would change the project's default profile. Put the file back as it was, and say so.
params_backup=$(mktemp)
cp params.yaml "$params_backup"
restore_params() {
  if ! cmp -s params.yaml "$params_backup"; then
    cp "$params_backup" params.yaml
    echo "pipeline: params.yaml put back as it was (dvc exp run -S profile=$PROFILE had written the override into it;" \
         "this run used profile=$PROFILE, recorded in dvc.lock and dvc exp show)" >&2
  fi
  rm -f "$params_backup"
}
trap 'restore_params; reattach' EXIT
echo "pipeline: profile=$PROFILE"
dvc exp run -S "profile=$PROFILE"
echo "pipeline: done. Tables and figures: reports/$PROFILE/README.md; runs: mlflow ui --backend-store-uri sqlite:///mlflow.db"
