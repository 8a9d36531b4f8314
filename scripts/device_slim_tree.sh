#!/usr/bin/env bash
# Make the working tree that the `device` tool sends to a lent GPU machine fit its 64 MiB limit, and put it back.
# The tracked tree is ~520 MB (docs/training/runs holds every run's weights + AdamW state), and the tool sends the
# tracked files plus untracked files git does not ignore. `slim` takes the big folders a pretraining run does not need
# out of the index (`git rm --cached`: the files stay on disk, untouched) and ignores them through .git/info/exclude, so
# they do not travel; `restore` puts the index and the exclude file back as they were. Nothing is committed either way:
# run `restore` before the next commit (`status` shows whether the tree is slim).
#   bash scripts/device_slim_tree.sh slim       # then the device `run` with carry [data/tokens/ext, data/tokens/rings_ext]
#   bash scripts/device_slim_tree.sh restore
#   bash scripts/device_slim_tree.sh status     # what would travel, in bytes
set -eu
cd "$(git rev-parse --show-toplevel)"
BIG=(docs benchmarks/reports tests/fixtures r1sim_sumo/checkpoints/r1sim-grpo)
EXCLUDE=.git/info/exclude
MARK="# device_slim_tree.sh"
travels() { (git ls-files -z; git ls-files -z -o --exclude-standard) | du --files0-from=- -cb 2>/dev/null | tail -1 | cut -f1; }
case "${1:-status}" in
  slim)
    if grep -q "$MARK" "$EXCLUDE" 2>/dev/null; then echo "already slim"; exit 0; fi
    if ! git diff --cached --quiet; then echo "the index has staged changes: commit or unstage them first" >&2; exit 1; fi
    git rm -r -q --cached "${BIG[@]}"
    for p in "${BIG[@]}"; do printf '/%s/\n' "$p"; done | sed "s|\$|\n$MARK|" >> "$EXCLUDE"
    echo "slim: $(travels) bytes of tracked + untracked files travel (plus what carry names)"
    ;;
  restore)
    git reset -q
    if [ -f "$EXCLUDE" ]; then
      python3 - "$EXCLUDE" "$MARK" <<'PY'
import sys
path, mark = sys.argv[1], sys.argv[2]
lines = open(path).read().splitlines()
keep, skip = [], False
for i, line in enumerate(lines):
    if i + 1 < len(lines) and lines[i + 1] == mark:
        continue  # the path line written by `slim`
    if line == mark:
        continue
    keep.append(line)
open(path, "w").write("\n".join(keep) + ("\n" if keep else ""))
PY
    fi
    echo "restored: $(travels) bytes would travel"
    ;;
  status)
    if grep -q "$MARK" "$EXCLUDE" 2>/dev/null; then echo "slim"; else echo "not slim"; fi
    echo "$(travels) bytes would travel (plus what carry names)"
    ;;
  *) echo "usage: $0 slim|restore|status" >&2; exit 2 ;;
esac
