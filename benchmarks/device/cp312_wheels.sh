# Sourced by bundle.sh and bundle_closed_loop.sh (the device's Python is CPython 3.12 on x86-64, this .venv's may be
# another): `cp312_wheels DIR` downloads CPython 3.12 manylinux x86-64 wheels of the names in the array `packages`,
# at this .venv's versions, into DIR, builds those in `sdists` (pure Python published without a wheel) there, and
# leaves every `name==version` in the array `pins`.
pin() { echo "$1==$(.venv/bin/python -c "import importlib.metadata as m; print(m.version('$1'))")"; }
cp312_wheels() {
  local dir=$1 p
  pins=()
  for p in "${packages[@]}"; do pins+=("$(pin "$p")"); done
  mkdir -p "$dir"
  .venv/bin/python -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: --python-version 3.12 \
    --implementation cp --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 \
    --platform manylinux_2_24_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
    -d "$dir" "${pins[@]}"
  for p in "${sdists[@]}"; do
    pins+=("$(pin "$p")")
    .venv/bin/python -m pip wheel -q --disable-pip-version-check --no-deps -w "$dir" "$(pin "$p")"
  done
}
