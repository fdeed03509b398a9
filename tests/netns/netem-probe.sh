#!/usr/bin/env bash
# Shows what coordinator/tests/netns.rs can and cannot emulate on this machine: it makes a
# veth pair and tries each traffic-control discipline the issue asks for. On the project's
# machines (kernel 6.18, no modules directory) `tbf` (rate) works and `netem` (latency,
# loss) fails with "Specified qdisc kind is unknown", so the namespace test limits rate with
# tbf and adds latency and loss in user space instead (a TUN relay in its switch namespace,
# coordinator/tests/netns/impair.rs). Needs root. Exit 0 when netem works.
set -u
A=strata-probe-a
ip link add "$A" type veth peer name strata-probe-b || { echo "cannot make a veth pair (root and CAP_NET_ADMIN needed)"; exit 2; }
trap 'ip link del "$A" 2>/dev/null' EXIT
echo "kernel $(uname -r)"
status=0
try() {
  local what=$1; shift
  if out=$(tc qdisc add dev "$A" root "$@" 2>&1); then
    echo "ok      $what (tc qdisc add ... $*)"
    tc qdisc del dev "$A" root 2>/dev/null
  else
    echo "FAILED  $what (tc qdisc add ... $*): $out"
    status=1
  fi
}
try "1 Gbit/s rate limit" tbf rate 1gbit burst 256kb latency 50ms
try "5 ms latency" netem delay 5ms
try "1 % loss" netem loss 1%
exit $status
