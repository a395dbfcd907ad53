#!/usr/bin/env bash
# The node built and installed the way a ROS 2 user does, without a ROS installation: colcon
# (PyPI colcon-core, colcon-ros, colcon-ros-cargo) and `cargo ament-build` from the ignored
# `.venv/` (scripts/setup_test_tools.sh), in a temporary workspace with this repository under
# src/. Checks:
#   1. package identification logs no ERROR or WARNING, and colcon builds vernier_ros;
#   2. the install tree: lib/vernier_ros/ holds the `detector` executable and nothing else;
#      share/vernier_ros/ holds package.xml, params/detector.yaml, the launch files and every
#      msg/*.msg; the ament index marks the package; install/setup.sh puts it on
#      AMENT_PREFIX_PATH;
#   3. the launch file (test/check_launch_file.py: `launch`/`launch_ros` are not on PyPI, so
#      its syntax, imports and the node it starts, not a real LaunchDescription);
#   4. the installed node, started from a shell that sourced install/setup.sh, detects in the
#      Cyclone DDS interop test (test/test_interop.py --installed, via test/run_in_netns.sh).
# The build goes into this repository's target directory (colcon's build/vernier_ros is a link
# to it; colcon leaves its colcon_build.rc and colcon_command_prefix_build.sh* there), so it
# reuses what cargo built before: `--cargo-args --release -p vernier_ros`, the release
# artifacts of `cargo build --release` and of the interop and bench tests; with
# VERNIER_ROS_PROFILE=test (CI), `--cargo-args -p vernier_ros`, the dev profile, whose
# dependencies are those `cargo test` built (the test profile differs only for workspace
# crates; cargo-ament-build cannot install from a named profile's folder).
# VERNIER_COLCON_WS=DIR keeps the workspace there instead of a temporary folder.
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$root"
bash scripts/setup_test_tools.sh >/dev/null
target_dir="$(cargo metadata --format-version 1 --no-deps --locked |
    grep -o '"target_directory":"[^"]*"' | cut -d'"' -f4)"
ws="${VERNIER_COLCON_WS:-$(mktemp -d /tmp/vernier_colcon.XXXXXX)}"
mkdir -p "$ws/src" "$ws/build"
ln -sfn "$root" "$ws/src/vernier_ros"
ln -sfn "$target_dir" "$ws/build/vernier_ros"
export PATH="$root/.venv/bin:$PATH"
fail=0
bad() { echo "FAIL $*"; fail=1; }
ok() { echo "PASS $*"; }

profile="${VERNIER_ROS_PROFILE:-release}"
case "$profile" in
release) cargo_args=(--release -p vernier_ros) ;;
test | dev) cargo_args=(-p vernier_ros) ;;
*) echo "VERNIER_ROS_PROFILE=$profile: release, test or dev" >&2; exit 2 ;;
esac
echo "== colcon build --packages-select vernier_ros --cargo-args ${cargo_args[*]} (in $ws)"
start=$SECONDS
(cd "$ws" && colcon build --packages-select vernier_ros --cargo-args "${cargo_args[@]}") \
    >"$ws/colcon.log" 2>&1 || { cat "$ws/colcon.log"; bad "colcon build"; exit 1; }
echo "colcon build: $((SECONDS - start)) s"
grep -q "^Finished <<< vernier_ros" "$ws/colcon.log" && ok "colcon built vernier_ros" ||
    { cat "$ws/colcon.log"; bad "colcon built vernier_ros"; }
# Without a ROS installation colcon-ros-cargo's build step warns that AMENT_PREFIX_PATH is
# empty (it looks there for other Rust ROS packages; this one has none): the one line allowed.
if grep -E "ERROR|WARNING" "$ws/colcon.log" | grep -v "AMENT_PREFIX_PATH is empty"; then
    bad "colcon logs no ERROR or WARNING (package identification included)"
else
    ok "colcon logs no ERROR or WARNING (package identification included)"
fi

echo "== install tree"
prefix="$ws/install/vernier_ros"
listing="$(cd "$prefix/lib/vernier_ros" && ls -A)"
[ "$listing" = detector ] && [ -x "$prefix/lib/vernier_ros/detector" ] &&
    ok "lib/vernier_ros holds the executable detector only" ||
    bad "lib/vernier_ros holds: $listing"
for f in package.xml params/detector.yaml launch_scripts/detector.launch.py \
    launch_scripts/detector.sh msg/*.msg; do
    if cmp -s "$root/$f" "$prefix/share/vernier_ros/$f"; then ok "share/vernier_ros/$f"; else
        bad "share/vernier_ros/$f missing or different"; fi
done
[ -f "$prefix/share/ament_index/resource_index/packages/vernier_ros" ] &&
    ok "ament index marker" || bad "ament index marker missing"
# A clean environment, as a user's new shell: only what install/setup.sh sets.
ament="$(env -i HOME="$HOME" PATH=/usr/bin:/bin sh -c \
    ". '$ws/install/setup.sh' && printf %s \"\$AMENT_PREFIX_PATH\"")"
case ":$ament:" in
*":$prefix:"*) ok "install/setup.sh puts $prefix on AMENT_PREFIX_PATH" ;;
*) bad "AMENT_PREFIX_PATH after install/setup.sh: '$ament'" ;;
esac

echo "== launch file"
"$root/.venv/bin/python" test/check_launch_file.py "$prefix" || bad "launch file"

echo "== the installed node in the Cyclone DDS interop test"
set +u
# shellcheck disable=SC1091
. "$ws/install/setup.sh"
set -u
VERNIER_ROS_FROM_INSTALL=1 VERNIER_ROS_PROFILE="$profile" \
    bash test/run_in_netns.sh "$root/test/test_interop.py" --installed || bad "installed node"

[ -n "${VERNIER_COLCON_WS:-}" ] || rm -rf "$ws"
[ "$fail" = 0 ] && echo "colcon: all checks passed" || { echo "colcon: FAILED"; exit 1; }
