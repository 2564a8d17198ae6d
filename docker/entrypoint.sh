#!/bin/sh
# Container entrypoint for sms-gateway (installed as /usr/local/bin/sms-gateway-entrypoint).
#   no arguments          -> sms-gateway --config "$SMS_GATEWAY_CONFIG" --listen "$SMS_GATEWAY_LISTEN"
#                            when that path exists, else the simulated bus:
#                            sms-gateway --simulate --listen "$SMS_GATEWAY_LISTEN"
#                            (defaults: /etc/sms-gateway/config.yaml and 0.0.0.0:502)
#   arguments "-..."      -> sms-gateway <arguments>       (e.g. --check-config FILE, --version)
#   anything else         -> run as given                  (e.g. sms-sim --help)
# The other SMS_GATEWAY_* variables (log level and format, allow-list, metrics, ...) are read by
# sms-gateway itself (config/README.md).
# exec keeps sms-gateway the process that receives SIGTERM (from the init, or as PID 1).
set -eu

config="${SMS_GATEWAY_CONFIG:-/etc/sms-gateway/config.yaml}"
# Inside the container the gateway serves on $SMS_GATEWAY_LISTEN, 0.0.0.0:502 by default (EXPOSE
# and HEALTHCHECK use 502); the host side is chosen with -p. --listen overrides the config's
# modbus_tcp.listen, so a config written for the host (127.0.0.1:5020, say) works unchanged.
# (sms-gateway reads SMS_GATEWAY_LISTEN itself too; the option makes the entrypoint's contract
# independent of that.)
listen="${SMS_GATEWAY_LISTEN:-0.0.0.0:502}"

# One log record on stderr, in the gateway's own format, so a log collector fed JSON lines
# (SMS_GATEWAY_LOG_FORMAT=json) never sees a plain line.
note() {
  if [ "${SMS_GATEWAY_LOG_FORMAT:-}" = json ]; then
    printf '{"ts":"%s","level":"info","logger":"sms-gateway-entrypoint","msg":"%s"}\n' \
           "$(date -u +%Y-%m-%dT%H:%M:%S.000Z)" "$1" >&2
  else
    echo "sms-gateway-entrypoint: $1" >&2
  fi
}

if [ "$#" -eq 0 ]; then
  # -e, not -f: a mount that went wrong (Docker creates a directory when the host file is
  # missing) must fail loudly in the config loader, not fall back to the simulator silently.
  if [ -e "$config" ]; then
    set -- --config "$config" --listen "$listen"
  else
    note "no config at $config; running the simulated bus (mount a config there to drive real servos)"
    set -- --simulate --listen "$listen"
  fi
fi

case "$1" in
  -*) set -- sms-gateway "$@" ;;
esac

exec "$@"
