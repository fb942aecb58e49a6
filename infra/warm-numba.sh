#!/bin/sh
# Compile streetcd's numba kernels into $NUMBA_CACHE_DIR at image build time: the demo runs on
# a tiny synthetic city (1 street, 3 images of 320x180, one worker), so that every kernel a
# view needs is compiled once here and not on each worker's first view (~30 s of a core).
# numba keys its cache by CPU name and features: the image sets NUMBA_CPU_NAME (generic by
# default) so that the cache built here is used on any x86-64 node.
set -eu
: "${NUMBA_CACHE_DIR:?set NUMBA_CACHE_DIR to the folder the workers will read}"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir -p "$NUMBA_CACHE_DIR"
# A temporary Prefect home: nothing of the demo's own Prefect server stays in the image.
PREFECT_HOME="$work/prefect" PREFECT_SERVER_ANALYTICS_ENABLED=false \
    streetcd demo --out "$work/demo" --streets 1 --images-per-street 3 --size 320x180 --workers 1
# The demo's tiny city has no pole near enough to a camera for the near points' fill
# (streetcd.detect.surface.fill_from_points): compile its kernel with the types a view passes.
python -c '
import numpy as np
from streetcd.detect.surface import _draw_discs
_draw_discs(np.zeros((1, 2)), np.ones(1), np.ones(1), np.full((2, 2), np.inf, np.float32),
            np.zeros((2, 2), np.float32), np.full((2, 2), -1, np.int32))
'
echo "numba cache: $(find "$NUMBA_CACHE_DIR" -name '*.nbc' | wc -l) compiled kernels in $NUMBA_CACHE_DIR"
