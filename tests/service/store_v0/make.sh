#!/usr/bin/env bash
# Make the upgrade test's fixture (tests/service/test_service_upgrade.py): a data directory written
# by the service as it was before the store had a schema version, and what that service answered.
#
#   bash tests/service/store_v0/make.sh [COMMIT]     (default: the commit before schema versions)
#
# The commit's tree is taken with `git archive` and run with this checkout's Python environment
# (the same dependencies); populate.py stores models and jobs through its server and client.
set -euo pipefail
commit=${1:-e9fef7c04d058ef59590e8b55c31154dbab74f4c}
here=$(cd "$(dirname "$0")" && pwd)
repo=$(git -C "$here" rev-parse --show-toplevel)
python=${PYTHON:-$repo/.venv/bin/python}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir "$work/src"
git -C "$repo" archive "$commit" | tar -x -C "$work/src"
(cd "$work" && PYTHONPATH="$work/src:$work/src/tests" "$python" "$here/populate.py" "$work/src" "$work/data" \
    "$here/expected.json")
rm -rf "$here/data"
cp -r "$work/data" "$here/data"
echo "$commit" > "$here/commit"
du -sh "$here/data"
