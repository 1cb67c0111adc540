# Sourced by the deploy scripts: process helpers.

# True if the process in pid file $1 runs; a killed one not yet reaped (a zombie) does not.
running() {
  [ -f "$1" ] || return 1
  local p
  p=$(cat "$1")
  kill -0 "$p" 2>/dev/null || return 1
  ! grep -q '^State:[[:space:]]*Z' "/proc/$p/status" 2>/dev/null
}
