#!/usr/bin/env bash
# End-to-end checks of the dtraced command line: exit codes, help, validation messages, and the
# render -> compare round trip. Needs DTRACED (the binary) and SCENES (the scenes folder).
set -uo pipefail

: "${DTRACED:?set DTRACED to the dtraced binary}"
: "${SCENES:?set SCENES to the scenes folder}"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

passed=0
failed=0
check() {  # check NAME EXPECTED_EXIT CMD...
  local name=$1 want=$2
  shift 2
  "$@" >"$work/out" 2>"$work/err"
  local got=$?
  if [ "$got" = "$want" ]; then
    passed=$((passed + 1))
  else
    failed=$((failed + 1))
    echo "FAIL: $name: exit $got, expected $want"
    sed 's/^/  stdout: /' "$work/out"
    sed 's/^/  stderr: /' "$work/err"
  fi
}
expect_text() {  # expect_text NAME FILE PATTERN
  if grep -q -- "$3" "$2"; then
    passed=$((passed + 1))
  else
    failed=$((failed + 1))
    echo "FAIL: $1: '$3' not found in:"
    sed 's/^/  /' "$2"
  fi
}

check "--version" 0 "$DTRACED" --version
expect_text "--version prints a version" "$work/out" "[0-9]\+\.[0-9]\+\.[0-9]\+"
expect_text "--version names its pixel version" "$work/out" "pixel version [1-9][0-9]*;"
check "--help" 0 "$DTRACED" --help
expect_text "--help lists render" "$work/out" "render"
for verb in render validate compare generate; do
  check "$verb --help" 0 "$DTRACED" "$verb" --help
done
check "no verb is a usage error" 2 "$DTRACED"
check "unknown verb" 2 "$DTRACED" frobnicate
check "unknown flag" 2 "$DTRACED" render "$SCENES/snowman.json" -o "$work/x.png" --no-such-flag
check "missing output" 2 "$DTRACED" render "$SCENES/snowman.json"
check "bad bit depth" 2 "$DTRACED" render "$SCENES/snowman.json" -o "$work/x.png" --bit-depth 12

check "validate good scenes" 0 "$DTRACED" validate "$SCENES"/*.json
expect_text "validate says OK" "$work/out" "OK"

cat >"$work/bad.json" <<'JSON'
{"camera": {"position": [0, 0, 5], "look_at": [0, 0, 0], "up": [0, 1, 0], "fov": 45},
 "scene_objects": [
   {"type": "sphere", "loc": [0, 0, 0], "radius": -1},
   {"type": "sphere", "loc": [0, 0, 0], "radius": 1, "material": {"ior": 0}}],
 "scene_lights": []}
JSON
check "validate a bad scene" 1 "$DTRACED" validate "$work/bad.json"
expect_text "error names the radius path" "$work/err" "bad.json: /scene_objects/0/radius"
expect_text "error names the ior path" "$work/err" "/scene_objects/1/material/ior"
check "render refuses a bad scene" 1 "$DTRACED" render "$work/bad.json" -o "$work/bad.png"
check "validate a missing file" 1 "$DTRACED" validate "$work/missing.json"
expect_text "missing file is named" "$work/err" "missing.json"

check "render png" 0 "$DTRACED" render "$SCENES/snowman.json" -o "$work/a.png" --width 64 --height 48 -s 2 -t 1
expect_text "summary line" "$work/err" "Mrays/s"
# -t 0 (the default) is the CPUs of the affinity mask, not the machine's: under taskset, one.
check "render under taskset" 0 taskset -c "$(taskset -pc $$ | sed 's/.*: *//; s/[-,].*//')" \
  "$DTRACED" render "$SCENES/snowman.json" -o "$work/t.png" --width 32 --height 24
expect_text "one CPU allowed, one render thread" "$work/err" "(1 threads,"
check "render the diffuse scene" 0 "$DTRACED" render "$SCENES/diffuse.json" -o "$work/d.png" --width 32 --height 24
expect_text "render prints the scene's features" "$work/err" "scene features: shadows point-lights (the tracer"
check "render the soft-shadow scene" 0 "$DTRACED" render "$SCENES/soft_shadows.json" -o "$work/s.png" --width 32 --height 24 -s 2
expect_text "area lights are a feature" "$work/err" "scene features: .*area-lights"
check "render pfm, other tiling" 0 "$DTRACED" render "$SCENES/snowman.json" -o "$work/a.pfm" --width 64 --height 48 -s 2 -t 2 --tile-size 7
check "render pfm, one thread" 0 "$DTRACED" render "$SCENES/snowman.json" -o "$work/b.pfm" --width 64 --height 48 -s 2 -t 1 --tile-size 64
check "compare identical" 0 "$DTRACED" compare "$work/a.pfm" "$work/b.pfm" --max-rmse 0
expect_text "identical images have rmse 0" "$work/out" "rmse 0 "
check "render ppm and 16-bit png" 0 "$DTRACED" render "$SCENES/snowman.json" -o "$work/a.ppm" --width 32 --height 24 -q
check "16-bit png" 0 "$DTRACED" render "$SCENES/snowman.json" -o "$work/a16.png" --width 32 --height 24 -q --bit-depth 16
check "different seed differs" 0 "$DTRACED" render "$SCENES/snowman.json" -o "$work/c.pfm" --width 64 --height 48 -s 2 --seed 99 -q
check "background override" 0 "$DTRACED" render "$SCENES/snowman.json" -o "$work/bg.pfm" --width 64 --height 48 -s 2 --background 1,0,0 -q
check "background override changes the image" 1 "$DTRACED" compare "$work/a.pfm" "$work/bg.pfm" --max-rmse 0
check "non-finite background is a usage error" 2 "$DTRACED" render "$SCENES/snowman.json" -o "$work/x.png" --background 1,nan,0
check "background needs three channels" 2 "$DTRACED" render "$SCENES/snowman.json" -o "$work/x.png" --background 1,0
check "compare with threshold fails" 1 "$DTRACED" compare "$work/a.pfm" "$work/c.pfm" --max-rmse 0
check "compare different sizes" 1 "$DTRACED" compare "$work/a.pfm" "$work/a16.png"
check "unsupported output extension" 2 "$DTRACED" render "$SCENES/snowman.json" -o "$work/a.tiff" -q
check "generate" 0 "$DTRACED" generate --count 500 --seed 3 -o "$work/gen.json"
check "generated scene validates" 0 "$DTRACED" validate "$work/gen.json"
check "generated scene writes plain decimals, no exponents" 1 grep -Eq '[0-9][eE][-+]?[0-9]' "$work/gen.json"
"$DTRACED" generate --count 50 --seed 4 -o "$work/gen2.json" 2>"$work/gen2.err"
"$DTRACED" validate "$work/gen2.json" >"$work/gen2.out" 2>&1
gen_digest=$(sed -n 's/.*digest \([0-9a-f]\{64\}\).*/\1/p' "$work/gen2.err")
check "a generated scene reads back to the digest generate printed" 0 grep -q "digest ${gen_digest:-missing}" "$work/gen2.out"

# Mesh scenes: generated with their OBJ files, validated, rendered; the scene names its files
# relative to itself, so it works from any directory.
check "generate a mesh scene" 0 "$DTRACED" generate --mesh-triangles 3000 --seed 5 -o "$work/m/mesh.json" --models-dir models
expect_text "the generator names its OBJ files" "$work/err" "3 OBJ files"
check "generate --count and --mesh-triangles exclude each other" 2 "$DTRACED" generate --count 5 --mesh-triangles 300 -o "$work/x.json"
check "the mesh scene validates" 0 "$DTRACED" validate "$work/m/mesh.json"
expect_text "validate counts triangles and degenerate ones" "$work/out" "degenerate triangles"
check "the mesh scene renders" 0 bash -c 'cd / && "$0" render "$1" -o "$2" --width 96 --height 54 -s 1' "$DTRACED" "$work/m/mesh.json" "$work/mesh.png"
expect_text "the summary names the kernels" "$work/err" "kernels"
check "the shipped mesh scene validates" 0 "$DTRACED" validate "$SCENES/mesh.json"
printf 'v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n' >"$work/m/bad.obj"
echo '{"camera": {}, "scene_objects": [{"type": "mesh", "file": "bad.obj"}], "scene_lights": []}' >"$work/m/bad.json"
check "a NaN in an OBJ is an error" 1 "$DTRACED" validate "$work/m/bad.json"
expect_text "the error names the scene, field, OBJ file and line" "$work/err" "bad.json: /scene_objects/0/file: bad.obj: line 2"

# Instruction sets: --isa, DTRACED_ISA, and --version naming the kernels that run.
check "--version names the kernels" 0 "$DTRACED" --version
expect_text "--version lists kernels and supported sets" "$work/out" "kernels: .*supported: scalar"
check "DTRACED_ISA is honoured by --version" 0 env DTRACED_ISA=scalar "$DTRACED" --version
expect_text "DTRACED_ISA=scalar shows in --version" "$work/out" "kernels: scalar;"
check "DTRACED_ISA is honoured by render" 0 env DTRACED_ISA=scalar "$DTRACED" render "$SCENES/snowman.json" -o "$work/isa.pfm" --width 32 --height 24
expect_text "render runs the scalar kernels" "$work/err" "scalar kernels"
check "--isa wins over DTRACED_ISA" 0 env DTRACED_ISA=bogus "$DTRACED" render "$SCENES/snowman.json" -o "$work/isa2.pfm" --width 32 --height 24 --isa best
check "every kernel renders the same bits" 0 "$DTRACED" compare "$work/isa.pfm" "$work/isa2.pfm" --max-rmse 0
check "--isa before the verb" 0 "$DTRACED" --isa scalar render "$SCENES/snowman.json" -o "$work/isa3.pfm" --width 32 --height 24 -q
check "a bad --isa is a usage error" 2 "$DTRACED" render "$SCENES/snowman.json" -o "$work/x.png" --isa sse9
expect_text "the bad --isa is named" "$work/err" "--isa sse9: not an instruction set"
check "a bad DTRACED_ISA is a usage error" 2 env DTRACED_ISA=sse9 "$DTRACED" render "$SCENES/snowman.json" -o "$work/x.png"
expect_text "the bad DTRACED_ISA is named" "$work/err" "DTRACED_ISA=sse9"
for isa in sse4 avx2 avx512; do
  if ! grep -q "supported:.* $isa" <("$DTRACED" --version); then
    check "an unsupported --isa is refused" 2 "$DTRACED" render "$SCENES/snowman.json" -o "$work/x.png" --isa "$isa"
    expect_text "the refusal lists what the CPU supports" "$work/err" "--isa $isa: this CPU supports scalar"
  fi
done
echo tok >"$work/token"
echo '{"role": "worker", "isa": "sse9"}' >"$work/w1.json"
check "a bad isa in a worker config" 2 "$DTRACED" --config "$work/w1.json" --collector http://127.0.0.1:1 --token-file "$work/token"
expect_text "the worker config's isa is checked" "$work/err" "sse9"
check "one-shot adaptive flags need --scene" 2 "$DTRACED" --role collector --error-target 0.05 --min-samples 4 --state-dir "$work/s" --token-file "$work/token"
expect_text "and say so" "$work/err" "--error-target, --min-samples are a one-shot job's: they need --scene"
check "--isa is not a collector option" 2 "$DTRACED" --role collector --isa scalar --state-dir "$work/s" --token-file "$work/token"

# Role configuration: JSON files, flags winning over them, unknown keys and misplaced flags.
echo '{"role": "collector", "listen": "127.0.0.1:0", "state_dir": "/nonexistent", "bogus_key": 1}' >"$work/c1.json"
check "config with an unknown key" 2 "$DTRACED" --config "$work/c1.json"
expect_text "the unknown key is named with its file" "$work/err" "c1.json: /bogus_key: unknown key"
echo '{"role": "collector", "state_dr": "/x"}' >"$work/c1b.json"
check "config with a misspelt key" 2 "$DTRACED" --config "$work/c1b.json"
expect_text "a misspelt key gets a suggestion, worded as in scenes and bodies" "$work/err" \
  'c1b.json: /state_dr: unknown key "state_dr" (did you mean "state_dir"?)'
echo '[1' >"$work/c2.json"
check "config that is not JSON" 2 "$DTRACED" --config "$work/c2.json" --role worker
expect_text "the bad config file is named" "$work/err" "c2.json"
expect_text "a syntax error in a config names the line" "$work/err" "invalid JSON at line 2, column 1"
check "a collector flag with --role worker" 2 "$DTRACED" --role worker --state-dir x --collector http://127.0.0.1:1 --token-file "$work/token"
check "a role and a verb together" 2 "$DTRACED" --role worker validate "$SCENES/snowman.json"
check "collector without a token file" 2 "$DTRACED" --role collector --state-dir "$work/s"
echo '{"listen": "127.0.0.1:bad"}' >"$work/c3.json"
check "a bad value in the config" 2 "$DTRACED" --role collector --config "$work/c3.json" --state-dir "$work/s" --token-file "$work/token"
# The flag wins over the config's bad listen address, so start-up gets as far as the state
# directory, which is a file here: a runtime failure (1), not a usage error (2).
: >"$work/not-a-dir"
check "flags win over the config" 1 "$DTRACED" --role collector --config "$work/c3.json" --listen 127.0.0.1:0 --state-dir "$work/not-a-dir" --token-file "$work/token"
# A read is retried for --timeout-ms when nothing answers (cli/retry.h): keep the wait short here.
check "client verb against no collector" 1 "$DTRACED" list --collector http://127.0.0.1:1 --timeout-ms 500
check "client verb with a bad URL" 1 "$DTRACED" list --collector https://example
# Adaptive sampling: the flags, the summary line, the spp map, and the same bits for any tiling.
ADAPT=(--width 48 --height 32 -s 32 --error-target 0.05 --min-samples 4)
check "adaptive render" 0 "$DTRACED" render "$SCENES/showcase.json" -o "$work/ad1.pfm" "${ADAPT[@]}" --spp-map "$work/spp.pfm" -t 2
expect_text "the summary gives the mean spp" "$work/err" "a mean [0-9.]* of at most 32 spp"
expect_text "the summary gives the share stopped early" "$work/err" "% of pixels stopped early"
check "adaptive render, other tiling" 0 "$DTRACED" render "$SCENES/showcase.json" -o "$work/ad2.pfm" "${ADAPT[@]}" -t 1 --tile-size 5 --spp-map "$work/spp2.pfm" -q
check "adaptive images match across tilings" 0 cmp "$work/ad1.pfm" "$work/ad2.pfm"
check "spp maps match across tilings" 0 cmp "$work/spp.pfm" "$work/spp2.pfm"
check "a 16-bit png spp map" 0 "$DTRACED" render "$SCENES/showcase.json" -o "$work/ad3.png" "${ADAPT[@]}" --spp-map "$work/spp.png" -q
check "an error target above 1 is a usage error" 2 "$DTRACED" render "$SCENES/showcase.json" -o "$work/x.png" --error-target 2
check "min samples 0 is a usage error" 2 "$DTRACED" render "$SCENES/showcase.json" -o "$work/x.png" --min-samples 0
check "a bad spp map extension" 2 "$DTRACED" render "$SCENES/showcase.json" -o "$work/x.png" --width 8 --height 8 --spp-map "$work/x.tiff"
check "submit takes adaptive flags" 2 "$DTRACED" submit "$SCENES/showcase.json" --collector http://127.0.0.1:1 --error-target -1

for verb in submit list status fetch cancel; do
  check "$verb --help" 0 "$DTRACED" "$verb" --help
done

# One override type: every override is a flag of render, submit and the one-shot collector, and
# bench error takes those that are not its own rows (samples, error target, min samples).
"$DTRACED" render --help >"$work/help-render" 2>&1
"$DTRACED" submit --help >"$work/help-submit" 2>&1
"$DTRACED" --help >"$work/help-top" 2>&1
"$DTRACED" bench error --help >"$work/help-bench" 2>&1
for flag in --width --height --samples --max-depth --seed --frame --background --error-target --min-samples --tile-size --bit-depth; do
  for where in render submit top; do
    expect_text "$flag is an override flag of $where" "$work/help-$where" "$flag"
  done
done
for flag in --width --height --max-depth --seed --frame --background --tile-size; do
  expect_text "$flag is an override flag of bench error" "$work/help-bench" "$flag"
done
check "one tile-size range: 1 is a tile side" 0 "$DTRACED" render "$SCENES/snowman.json" -o "$work/t1.pfm" --width 4 --height 3 --tile-size 1 -q
check "one tile-size range: 2048 is not" 2 "$DTRACED" render "$SCENES/snowman.json" -o "$work/x.pfm" --tile-size 2048
check "submit checks the background" 2 "$DTRACED" submit "$SCENES/snowman.json" --collector http://127.0.0.1:1 --background 1,-1,0
check "submit checks the bit depth" 2 "$DTRACED" submit "$SCENES/snowman.json" --collector http://127.0.0.1:1 --bit-depth 12

# Did-you-mean: an unknown verb or flag is answered with the nearest one of its command.
check "a misspelt verb" 2 "$DTRACED" rendr "$SCENES/snowman.json"
expect_text "a misspelt verb gets the nearest verb" "$work/err" "rendr: did you mean render?"
check "a misspelt flag of a verb" 2 "$DTRACED" render "$SCENES/snowman.json" -o "$work/x.png" --sampels 4
expect_text "a misspelt flag gets the verb's nearest flag" "$work/err" "--sampels: did you mean --samples?"
check "a misspelt role flag" 2 "$DTRACED" --role collector --stat-dir "$work/s" --token-file "$work/token"
expect_text "a misspelt role flag gets the nearest flag" "$work/err" "--stat-dir: did you mean --state-dir?"
check "the seed's -vpw" 2 "$DTRACED" render "$SCENES/snowman.json" -o "$work/x.png" -vpw 64
expect_text "the seed's -vpw is mapped to --width" "$work/err" "the seed's -vpw is dtraced's --width"

# A bad value is named by its flag when it came from the command line, by the config file and
# its key when it came from --config.
check "collector without a state dir" 2 "$DTRACED" --role collector --token-file "$work/token"
expect_text "the missing state dir is named by its flag" "$work/err" "^--state-dir: must not be empty"
check "a bad --listen on the command line" 2 "$DTRACED" --role collector --listen 127.0.0.1:bad --state-dir "$work/s" --token-file "$work/token"
expect_text "the bad listen address is named by its flag" "$work/err" '^--listen: bad port "bad"'
check "a bad listen in the config" 2 "$DTRACED" --role collector --config "$work/c3.json" --state-dir "$work/s" --token-file "$work/token"
expect_text "the bad listen address is named by the config file and key" "$work/err" 'c3.json: /listen: bad port "bad"'
echo '{"role": "collector", "state_dir": ""}' >"$work/c5.json"
check "an empty state dir in the config" 2 "$DTRACED" --config "$work/c5.json" --token-file "$work/token"
expect_text "the empty state dir is named by the config file and key" "$work/err" "c5.json: /state_dir: must not be empty"
echo '{"role": "collector", "max-connections": 0}' >"$work/c6.json"
check "an out-of-range number in the config" 2 "$DTRACED" --config "$work/c6.json" --state-dir "$work/s" --token-file "$work/token"
expect_text "the refused number is named by the config file and key as spelt" "$work/err" "c6.json: /max-connections: Value 0 not in range"
check "an out-of-range number on the command line" 2 "$DTRACED" --role collector --max-connections 0 --state-dir "$work/s" --token-file "$work/token"
expect_text "the refused number is named by its flag" "$work/err" "^--max-connections: Value 0 not in range"
echo '{"role": "worker", "collector": "ftp://example"}' >"$work/w2.json"
check "a bad collector URL in a worker config" 2 "$DTRACED" --config "$work/w2.json" --token-file "$work/token"
expect_text "the worker's URL is named by the config file and key" "$work/err" "w2.json: /collector: URL 'ftp://example' must start with http://"
check "a bad collector URL on the command line" 2 "$DTRACED" --role worker --collector ftp://example --token-file "$work/token"
expect_text "the worker's URL is named by its flag" "$work/err" "^--collector: URL"
printf 'has space\n' >"$work/token-space"
check "a token with a space" 2 "$DTRACED" --role collector --state-dir "$work/s" --token-file "$work/token-space"
expect_text "the token's problem is named by --token-file" "$work/err" "^--token-file: the token it holds: must be printable ASCII"

# A token file that cannot be read says it is the token file, with its path and the reason.
check "collector with a missing token file" 2 "$DTRACED" --role collector --state-dir "$work/s" --token-file "$work/no-token"
expect_text "the collector names the missing token file" "$work/err" "no-token: cannot open the token file: No such file or directory"
check "worker with a missing token file" 2 "$DTRACED" --role worker --collector http://127.0.0.1:1 --token-file "$work/no-token"
expect_text "the worker names the missing token file" "$work/err" "no-token: cannot open the token file: No such file or directory"
check "client verb with a missing token file" 1 "$DTRACED" list --collector http://127.0.0.1:1 --token-file "$work/no-token"
expect_text "a client verb names the missing token file" "$work/err" "no-token: cannot open the token file: No such file or directory"
check "a directory as the token file" 2 "$DTRACED" --role worker --collector http://127.0.0.1:1 --token-file "$work"
expect_text "a directory is not a token file" "$work/err" "the token file is a directory"
: >"$work/empty-token"
check "an empty token file" 1 "$DTRACED" status 1 --collector http://127.0.0.1:1 --token-file "$work/empty-token"
expect_text "an empty token file says so" "$work/err" "empty-token: the token file is empty"

# --listen takes host names, resolved at start.
check "a --listen name that does not resolve" 2 "$DTRACED" --role collector --listen nosuch.invalid:0 --state-dir "$work/s" --token-file "$work/token"
expect_text "the unresolved name is named" "$work/err" '^--listen: cannot resolve the host name "nosuch.invalid"'
"$DTRACED" --role collector --listen localhost:0 --state-dir "$work/s-localhost" --token-file "$work/token" 2>"$work/localhost.log" &
localhost_pid=$!
for _ in $(seq 1 300); do
  grep -q "listening on" "$work/localhost.log" && break
  kill -0 "$localhost_pid" 2>/dev/null || break
  sleep 0.1
done
expect_text "a collector listens on localhost:0" "$work/localhost.log" "listening on 127.0.0.1 port [1-9]"
kill -TERM "$localhost_pid" 2>/dev/null
wait "$localhost_pid"
check "a collector on localhost stops cleanly on SIGTERM" 0 test "$?" = 0

# The farm limits (issue 17): in --help, bounded, named by flag or by config key, role-checked.
for flag in --max-idle-connections --max-workers --max-idle-wait-ms --start-jitter-ms; do
  expect_text "--help lists $flag" "$work/help-top" "$flag"
done
expect_text "--help says idle connections follow --max-connections" "$work/help-top" "default: --max-connections"
check "--max-workers 0" 2 "$DTRACED" --role collector --max-workers 0 --state-dir "$work/s" --token-file "$work/token"
expect_text "--max-workers 0 is named by its flag" "$work/err" "^--max-workers: Value 0 not in range"
check "--max-idle-wait-ms over the protocol's limit" 2 "$DTRACED" --role collector --max-idle-wait-ms 60001 --state-dir "$work/s" --token-file "$work/token"
expect_text "--max-idle-wait-ms is named by its flag" "$work/err" "^--max-idle-wait-ms: Value 60001 not in range"
echo '{"role": "collector", "max_idle_connections": 0}' >"$work/c7.json"
check "max_idle_connections 0 in the config" 2 "$DTRACED" --config "$work/c7.json" --state-dir "$work/s" --token-file "$work/token"
expect_text "max_idle_connections is named by the config file and key" "$work/err" "c7.json: /max_idle_connections: Value 0 not in range"
check "--start-jitter-ms is a worker flag" 2 "$DTRACED" --role collector --start-jitter-ms 10 --state-dir "$work/s" --token-file "$work/token"
expect_text "--start-jitter-ms on a collector is refused" "$work/err" "start-jitter-ms is not an option of --role collector"
check "--start-jitter-ms over an hour" 2 "$DTRACED" --role worker --collector http://127.0.0.1:1 --start-jitter-ms 3600001 --token-file "$work/token"
# A worker waiting out its start jitter exits 0 on SIGTERM at once, having asked nothing.
echo '{"role": "worker", "start_jitter_ms": 3600000}' >"$work/w3.json"
"$DTRACED" --config "$work/w3.json" --collector "http://127.0.0.1:1" --name jittery --token-file "$work/token" 2>"$work/jitter.log" &
jitter_pid=$!
for _ in $(seq 1 300); do
  grep -q "before the first request" "$work/jitter.log" && break
  kill -0 "$jitter_pid" 2>/dev/null || break
  sleep 0.1
done
expect_text "the worker says how long it waits before its first request" "$work/jitter.log" "jittery: waiting [0-9]* ms before the first request (--start-jitter-ms 3600000)"
kill -TERM "$jitter_pid" 2>/dev/null
wait "$jitter_pid"
check "a worker stopped during its start jitter exits 0" 0 test "$?" = 0
# It asked nothing (the address refuses connections: a lease request would have failed).
expect_text "a worker stopped during its start jitter asked nothing" "$work/jitter.log" " 0 lease failures"

# render prints the warnings validate prints.
echo '{"camera": {"position": [0, 0, 5], "look_at": [0, 0, 0], "up": [0, 1, 0], "fov": 45},
 "scene_objects": [{"type": "sphere", "loc": [0, 0, 0], "radius": 1}], "scene_lights": []}' >"$work/nolights.json"
check "validate a scene without lights" 0 "$DTRACED" validate "$work/nolights.json"
grep '^warning:' "$work/err" >"$work/validate-warnings"
expect_text "validate warns about the missing lights" "$work/validate-warnings" "/scene_lights"
check "render a scene without lights" 0 "$DTRACED" render "$work/nolights.json" -o "$work/nolights.png" --width 8 --height 8 -q
grep '^warning:' "$work/err" >"$work/render-warnings"
check "render prints the same warnings as validate" 0 cmp "$work/validate-warnings" "$work/render-warnings"

# Output paths are checked before the render starts (which may take hours): the error names the
# flag and the directory, the exit code is 2, and nothing is written.
check "render into a missing directory is a usage error" 2 "$DTRACED" render "$SCENES/showcase.json" -o "$work/missing/x.png" -q
expect_text "and names the directory" "$work/err" "^--output: $work/missing: the output directory does not exist"
echo "not a directory" >"$work/plainfile"
check "render into a file's path is a usage error" 2 "$DTRACED" render "$SCENES/snowman.json" -o "$work/plainfile/x.png" -q
expect_text "and names the file in the way" "$work/err" "$work/plainfile: the output's directory is not a directory"
check "an spp map into a missing directory is a usage error" 2 "$DTRACED" render "$SCENES/snowman.json" -o "$work/y.png" --spp-map "$work/missing/s.pfm" -q
expect_text "and names --spp-map" "$work/err" "^--spp-map: $work/missing"
[ ! -e "$work/y.png" ] && passed=$((passed + 1)) || { failed=$((failed + 1)); echo "FAIL: a refused render wrote its image"; }
check "a one-shot collector's output in a missing directory is a usage error" 2 "$DTRACED" --role collector --scene "$SCENES/snowman.json" -o "$work/missing/shot.png" --state-dir "$work/s1" --token-file "$work/token" --listen 127.0.0.1:0
expect_text "and names the directory" "$work/err" "$work/missing: the output directory does not exist"
[ ! -e "$work/s1" ] && passed=$((passed + 1)) || { failed=$((failed + 1)); echo "FAIL: a refused one-shot collector made its state directory"; }

echo "$passed passed, $failed failed"
[ "$failed" = 0 ]
