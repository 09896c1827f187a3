#!/usr/bin/env bash
# Prepare what a borrowed GPU machine lacks for scripts/gpu_campaign.py, under .gpu/ (git-ignored;
# copy `.gpu` to the GPU machine with the working tree):
#   .gpu/site.tar.xz   mujoco 3.17.0, dm-control 1.0.50 (trimmed: no locomotion assets, no dog
#                      meshes, no MuJoCo studio), mcap, mcap-ros2-support, tyro and dm_control's pure
#                      dependencies, as CPython wheels for the GPU machine's Python (default 3.12)
#   .gpu/prefix/share/<pkg>/msg/*.msg|*.json   the message definitions the MCAP writer reads
#                      (the GPU path has no ROS install; see trainer/bag/__init__.py)
# About 16 MB in all. On the GPU machine:
#   python scripts/gpu_campaign.py --site-archive .gpu/site.tar.xz --ament-prefix .gpu/prefix
#
#   scripts/gpu_pack.sh [PYTHON_VERSION]      (run inside the project's environment)
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
PYVER="${1:-3.12}"
OUT="$ROOT/.gpu"
WORK="$(mktemp -d)"
trap 'rm -rf "$WORK"' EXIT
SITE="$WORK/site"

python -m pip install -q --target "$SITE" --python-version "$PYVER" --implementation cp \
  --only-binary=:all: --no-deps \
  --platform manylinux2014_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux_2_28_x86_64 \
  mujoco==3.17.0 dm-control==1.0.50 mcap==1.6.0 mcap-ros2-support==0.6.0 \
  dm-env dm-tree absl-py pyopengl lxml glfw etils zstandard tyro==1.0.17 docstring-parser typeguard typing-extensions
# What the eight suite tasks never load (85 MB of locomotion/manipulation assets and more).
rm -rf "$SITE"/dm_control/locomotion "$SITE"/dm_control/suite/dog_assets \
       "$SITE"/dm_control/suite/all_domains.png "$SITE"/mujoco/experimental
find "$SITE" -name __pycache__ -prune -exec rm -rf {} +
find "$SITE" -name '*_test.py' -delete

mkdir -p "$OUT"
tar -cJf "$OUT/site.tar.xz.tmp" -C "$WORK" site
mv "$OUT/site.tar.xz.tmp" "$OUT/site.tar.xz"
rm -rf "$OUT/prefix"
for pkg in builtin_interfaces std_msgs sensor_msgs geometry_msgs rosgraph_msgs diagnostic_msgs; do
  src="$(python -c "from ament_index_python.packages import get_package_share_directory as g; print(g('$pkg'))")"
  mkdir -p "$OUT/prefix/share/$pkg/msg" "$OUT/prefix/share/ament_index/resource_index/packages"
  cp "$src"/msg/*.msg "$src"/msg/*.json "$OUT/prefix/share/$pkg/msg/" 2>/dev/null || cp "$src"/msg/*.msg "$OUT/prefix/share/$pkg/msg/"
  touch "$OUT/prefix/share/ament_index/resource_index/packages/$pkg"
done
du -sh "$OUT"/site.tar.xz "$OUT"/prefix
