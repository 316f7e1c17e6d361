#!/usr/bin/env bash
# Pack a demo folder for the trip back from a lent GPU machine (gpu_session.sh, gpu_lease.sh):
#
#   bash scripts/pack_demo.sh DEMO_DIR OUT.tar.gz
#
# writes OUT.tar.gz (the folder without run/checkpoints); when that is over 15 MiB (the device tool brings back
# files of at most 16 MiB: a paper-scale network's weights alone are 16 MiB) it is split into OUT.tar.gz.part-aa,
# OUT.tar.gz.part-ab, … of 15 MiB each, rejoined here with `cat OUT.tar.gz.part-* > OUT.tar.gz`. Prints what it
# wrote.
set -euo pipefail
if [[ $# -ne 2 || ! -d "$1" ]]; then
    echo "usage: bash scripts/pack_demo.sh DEMO_DIR OUT.tar.gz (DEMO_DIR a folder)" >&2
    exit 2
fi
src=$1
dest=$2
rm -f "$dest" "$dest".part-*
rc=0  # 1: a file changed while it was read (a run still saving): packed as it was, kept
tar --warning=no-file-changed -czf "$dest" -C "$src" --exclude='run/checkpoints' . || rc=$?
if (( rc > 1 )); then
    echo "pack_demo.sh: tar failed (exit $rc)" >&2
    exit "$rc"
fi
if (( $(stat -c %s "$dest") > 15 * 1024 * 1024 )); then
    split -b 15M "$dest" "$dest.part-"
    rm -f "$dest"
    echo "packed $src into $(ls "$dest".part-* | wc -l) parts: cat $(basename "$dest").part-* > $(basename "$dest")"
else
    echo "packed $src into $(basename "$dest")"
fi
