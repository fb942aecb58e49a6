#!/bin/sh
# Register the nightly deployment (infra/prefect.yaml) with the Prefect server at
# $PREFECT_API_URL, then run a Prefect worker of the process pool "streetcd" that runs its flow
# runs. Used by docker-compose.yml (service flow-worker); works from any folder.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
pool=streetcd

# Create the pool once; an existing one (maybe with limits set in the UI) is kept as it is.
prefect work-pool inspect "$pool" >/dev/null 2>&1 || prefect work-pool create "$pool" --type process

# `prefect deploy` (Prefect 3.8.8) registers the deployment and then asks for the pool's online
# workers, only to print a hint. With FastAPI 0.154 (constraints.txt) the server answers that
# request with 422 ('limit': Input should be a valid integer; the client sends null) and deploy
# exits 1 although the deployment was saved. Only that failure, after that success, is let
# through; any other deploy error stops here.
log=$(mktemp)
trap 'rm -f "$log"' EXIT
if prefect --no-prompt deploy --all --prefect-file "$here/prefect.yaml" >"$log" 2>&1; then
    cat "$log"
elif grep -q "successfully created" "$log" && grep -q "/workers/filter" "$log" \
        && grep -q "422 Unprocessable Entity" "$log"; then
    grep -v "^ " "$log" | grep -v "^Traceback" | grep -v "^prefect.exceptions" \
        | grep -v "^An exception occurred" || true
    echo "deploy: deployment saved; the server's 422 on the workers/filter hint is ignored (see infra/README.md)"
else
    cat "$log" >&2
    exit 1
fi
exec prefect worker start --pool "$pool"
