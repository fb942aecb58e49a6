#!/bin/sh
# The image's entrypoint: runs its arguments (compose's `command`, Kubernetes' `args`).
# The dask Helm chart starts its pods with the names `dask-scheduler` and `dask-worker` (the
# scheduler's is fixed in the chart's template), which distributed 2026.x no longer installs;
# they become `dask scheduler` and `dask worker`, the same programs with the same options.
set -eu
case "${1:-}" in
    dask-scheduler) shift; exec dask scheduler "$@" ;;
    dask-worker) shift; exec dask worker "$@" ;;
    "") echo "usage: <command> [args...], e.g. dask scheduler, dask worker, infra/flow-worker.sh" >&2; exit 2 ;;
esac
exec "$@"
