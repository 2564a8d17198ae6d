#!/bin/sh
# Container entrypoint for sms-gateway (installed as /usr/local/bin/sms-gateway-entrypoint).
#   no arguments          -> sms-gateway --config "$SMS_GATEWAY_CONFIG" --listen "$SMS_GATEWAY_LISTEN"
#                            when that path exists, else the simulated bus:
#                            sms-gateway --simulate --listen "$SMS_GATEWAY_LISTEN"
#                            (defaults: /etc/sms-gateway/config.yaml and 0.0.0.0:502)
#   arguments "-..."      -> sms-gateway <arguments>       (e.g. --check-config FILE, --version)
#   anything else         -> run as given                  (e.g. sms-sim --help)
# exec keeps sms-gateway the process that receives SIGTERM (from the init, or as PID 1).
set -eu

config="${SMS_GATEWAY_CONFIG:-/etc/sms-gateway/config.yaml}"
# Inside the container the gateway serves on $SMS_GATEWAY_LISTEN, 0.0.0.0:502 by default (EXPOSE
# and HEALTHCHECK use 502); the host side is chosen with -p. --listen overrides the config's
# modbus_tcp.listen, so a config written for the host (127.0.0.1:5020, say) works unchanged.
listen="${SMS_GATEWAY_LISTEN:-0.0.0.0:502}"

if [ "$#" -eq 0 ]; then
  # -e, not -f: a mount that went wrong (Docker creates a directory when the host file is
  # missing) must fail loudly in the config loader, not fall back to the simulator silently.
  if [ -e "$config" ]; then
    set -- --config "$config" --listen "$listen"
  else
    echo "sms-gateway-entrypoint: no config at $config; running the simulated bus" \
         "(mount a config there to drive real servos)" >&2
    set -- --simulate --listen "$listen"
  fi
fi

case "$1" in
  -*) set -- sms-gateway "$@" ;;
esac

exec "$@"
