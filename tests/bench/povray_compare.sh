#!/usr/bin/env bash
# dtraced against POV-Ray 3.7 on whole images: the same scenes (tests/bench/povray_scenes.py
# writes each one for both renderers), the same size, 1 and 2 threads. A benchmark, not a test:
# it prints figures with MET/MISSED against issue 16's targets and fails only when it cannot run.
#
# Two comparisons per scene and thread count:
#   no antialiasing  dtraced -s 1 against POV-Ray -A; render phase only (dtraced's "rendered ... in
#                    X s", POV-Ray's "Trace Time"), medians of RUNS. Target: POV / dtraced >= 3.
#   equal error      each renderer's PSNR against its own converged reference (dtraced: REF_SPP
#                    samples with a seed of their own, so its noise is independent; POV-Ray: +A0.0 +R8, 64 jittered rays a pixel), both 16-bit PNG
#                    through `dtraced compare`. POV-Ray's points are +A0.3 +R3 and +A0.1 +R3; for
#                    each, the dtraced setting of a ladder (uniform and adaptive) with the fewest
#                    rays per pixel whose PSNR is at least POV-Ray's, timed RUNS times.
#                    Target: POV / dtraced >= 2.
# The shading models are matched as closely as POV-Ray allows (povray_scenes.py says what
# differs); each renderer is judged against its own reference, so that difference is not error.
# Both scenes carry POV-Ray's default branch cut-off (adc_bailout 1/255; dtraced's
# render.branch_cutoff); dtraced's reference is rendered at its default cut-off (1e-6) instead, so
# what the cut-off loses counts against dtraced (POV-Ray's reference keeps its own bailout).
# The images of each pair are written next to each other in OUT/index.html.
#
# Setup: POV-Ray is installed here (apt-get install povray, as root) when missing; the product
# itself never needs it. Then, after the README's build:
#   tests/bench/povray_compare.sh
# Environment: DTRACED (build/src/cli/dtraced), SCENES ("whitted10 spheres10k"), WIDTH (1280),
# HEIGHT (720), THREADS ("1 2", capped at nproc), RUNS (5), REF_SPP (256), OUT (build/bench-povray:
# images, references cached by scene, size and REF_SPP, index.html), LADDER (dtraced settings
# tried for the equal-error comparison, ';'-separated).
# A first run on 2 cores takes about 30-40 minutes, most of it the references; later runs reuse them.
set -uo pipefail
export LC_ALL=C

root=$(cd "$(dirname "$0")/../.." && pwd)
DTRACED=${DTRACED:-$root/build/src/cli/dtraced}
SCENES=${SCENES:-"whitted10 spheres10k"}
WIDTH=${WIDTH:-1280}
HEIGHT=${HEIGHT:-720}
THREADS=${THREADS:-"1 2"}
RUNS=${RUNS:-5}
REF_SPP=${REF_SPP:-256}
REF_SEED=977 # not the scenes' own seed: a reference sharing the renders' samples would flatter them
OUT=${OUT:-$root/build/bench-povray}
# The ladder: uniform, then adaptive from a first checkpoint of 1 sample (the neighbourhood
# decides, like POV-Ray's antialiasing threshold) up to tight targets; settings between -s 4 and
# the adaptive ones at 4 so that the cheapest one reaching POV-Ray's error does not overshoot it;
# at -s 16 -N 1, targets 0.1 and 0.09 as well as 0.08, whose 50.4 dB on whitted10 overshot
# POV-Ray's +A0.3 and +A0.1 (48.9, 49.5 dB) by 1-1.5 dB (0.1: 49.4 dB at 8 % fewer rays), and
# 0.105 (49.0 dB on whitted10 at 1.7 % fewer rays than 0.1; 0.11 gave 48.8 dB, short of +A0.3).
LADDER=${LADDER:-"-s 2;-s 4;-s 8;-s 16;-s 16 --min-samples 1 --error-target 0.105;-s 16 --min-samples 1 --error-target 0.1;-s 16 --min-samples 1 --error-target 0.09;-s 16 --min-samples 1 --error-target 0.08;-s 32 --min-samples 1 --error-target 0.32;-s 32 --min-samples 1 --error-target 0.24;-s 32 --min-samples 1 --error-target 0.2;-s 32 --min-samples 1 --error-target 0.16;-s 32 --min-samples 1 --error-target 0.12;-s 32 --min-samples 1 --error-target 0.08;-s 32 --min-samples 2 --error-target 0.12;-s 32 --min-samples 2 --error-target 0.08;-s 32 --min-samples 4 --error-target 0.16;-s 32 --min-samples 4 --error-target 0.08;-s 32 --min-samples 4 --error-target 0.04;-s 64 --min-samples 4 --error-target 0.01"}

fail() {
  echo "povray_compare: $*" >&2
  exit 1
}

[ -x "$DTRACED" ] || fail "no dtraced at $DTRACED (build first: cmake -B build && cmake --build build)"
if ! command -v povray >/dev/null; then
  [ "$(id -u)" = 0 ] || fail "POV-Ray is not installed and this is not root: apt-get install povray"
  echo "installing POV-Ray (Debian's povray; the benchmark's own setup)"
  { apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends povray; } >/dev/null ||
    fail "could not install povray"
fi
mkdir -p "$OUT" || fail "cannot create $OUT"
cores=$(nproc)

median() { printf '%s\n' "$@" | sort -g | awk '{ v[NR] = $1 } END { print (NR % 2) ? v[(NR + 1) / 2] : (v[NR / 2] + v[NR / 2 + 1]) / 2 }'; }
ratio() { awk -v a="$1" -v b="$2" 'BEGIN { printf "%.2f", a / b }'; }
verdict() { awk -v r="$1" -v t="$2" 'BEGIN { print (r >= t) ? "MET" : "MISSED" }'; }

# dtraced_line SCENE OUTPUT THREADS ARGS...: prints dtraced's "rendered ..." line.
dtraced_line() {
  local scene=$1 out=$2 t=$3
  shift 3
  # A run interrupted earlier may have left a resume file, which `render` would refuse to ignore.
  rm -f "$out.partial"
  "$DTRACED" render "$scene" -o "$out" --width "$WIDTH" --height "$HEIGHT" --bit-depth 16 -t "$t" "$@" 2>&1 |
    grep '^rendered ' || fail "dtraced render $scene $* failed"
}

# dtraced_render SCENE OUTPUT THREADS ARGS...: prints the render phase in seconds.
dtraced_render() {
  local line
  line=$(dtraced_line "$@") || exit 1
  sed -n 's/.* in \([0-9.]*\) s .*/\1/p' <<<"$line"
}

# pov_render SCENE OUTPUT THREADS ARGS...: prints POV-Ray's trace time in seconds.
pov_render() {
  local scene=$1 out=$2 t=$3 log
  shift 3
  log=$(povray +I"$scene" +O"$out" +W"$WIDTH" +H"$HEIGHT" +WT"$t" -D -P +FN16 File_Gamma=sRGB "$@" 2>&1) ||
    fail "povray $scene $* failed: $(tail -n 5 <<<"$log")"
  sed -n 's/.*Trace Time:.*(\([0-9.]*\) seconds).*/\1/p' <<<"$log"
}

# psnr A B: the PSNR of A against B in dB (`dtraced compare`).
psnr() { "$DTRACED" compare "$1" "$2" | sed -n 's/.*psnr \([0-9.inf]*\) dB.*/\1/p'; }

html="$OUT/index.html"
printf '<!doctype html><meta charset="utf-8"><title>dtraced vs POV-Ray</title>\n<h1>dtraced vs POV-Ray 3.7, %sx%s</h1>\n' \
  "$WIDTH" "$HEIGHT" >"$html"
html_pair() { # html_pair CAPTION LEFT_CAPTION LEFT RIGHT_CAPTION RIGHT
  printf '<h2>%s</h2><div style="display:flex;gap:8px"><figure><img src="%s" width="640"><figcaption>%s</figcaption></figure><figure><img src="%s" width="640"><figcaption>%s</figcaption></figure></div>\n' \
    "$1" "${3#"$OUT"/}" "$2" "${5#"$OUT"/}" "$4" >>"$html"
}

echo "dtraced vs POV-Ray $(povray --version 2>&1 | sed -n 's/^POV-Ray \([0-9][0-9.]*[0-9]\).*/\1/p' | head -n1): $cores CPUs, load average $(cut -d' ' -f1-3 /proc/loadavg)"
echo "images ${WIDTH}x${HEIGHT}, render phase only, medians of $RUNS; references: dtraced $REF_SPP spp, POV-Ray +A0.0 +R8"
summary=()
for name in $SCENES; do
  dir="$OUT/$name-${WIDTH}x${HEIGHT}"
  mkdir -p "$dir"
  python3 "$root/tests/bench/povray_scenes.py" "$name" "$dir" "$WIDTH" "$HEIGHT" || fail "cannot write scene $name"
  json="$dir/$name.json" pov="$dir/$name.pov" ref_json="$dir/$name-ref.json"
  top=$(for t in $THREADS; do [ "$t" -le "$cores" ] && echo "$t"; done | sort -n | tail -n1)
  [ -n "$top" ] || fail "no thread count in THREADS fits $cores CPUs"

  # References, once per scene, size and REF_SPP (kept in $dir).
  dref="$dir/ref-dtraced-$REF_SPP-seed$REF_SEED.png" pref="$dir/ref-povray.png"
  if [ ! -s "$dref" ]; then
    echo "$name: dtraced reference ($REF_SPP spp)..."
    dtraced_render "$ref_json" "$dref.tmp.png" "$top" -s "$REF_SPP" --seed "$REF_SEED" >/dev/null && mv "$dref.tmp.png" "$dref"
  fi
  if [ ! -s "$pref" ]; then
    echo "$name: POV-Ray reference (+A0.0 +R8)..."
    pov_render "$pov" "$pref.tmp.png" "$top" +A0.0 +AM1 +R8 >/dev/null && mv "$pref.tmp.png" "$pref"
  fi

  # The equal-error ladder: every setting once at the top thread count, for its PSNR.
  IFS=';' read -r -a ladder <<<"$LADDER"
  # Also its mean samples and rays per pixel: deterministic, so a cost that load cannot blur.
  ladder_psnr=() ladder_cost=() ladder_rays=()
  for i in "${!ladder[@]}"; do
    read -r -a args <<<"${ladder[$i]}"
    line=$(dtraced_line "$json" "$dir/dtraced-ladder-$i.png" "$top" "${args[@]}") || exit 1
    ladder_psnr+=("$(psnr "$dir/dtraced-ladder-$i.png" "$dref")")
    spp=$(sed -n 's/.* at a mean \([0-9.]*\) of .*/\1/p; s/.* at \([0-9]*\) spp .*/\1/p' <<<"$line")
    rays=$(sed -n 's/.*: \([0-9.]*\) M rays.*/\1/p' <<<"$line")
    ladder_rays+=("$(awk -v r="$rays" -v n=$((WIDTH * HEIGHT)) 'BEGIN { printf "%.1f", r * 1e6 / n }')")
    ladder_cost+=("$spp spp, ${ladder_rays[$i]} rays/pixel")
  done

  echo
  echo "## $name"
  echo
  echo "| threads | mode | POV-Ray setting | POV-Ray s | POV-Ray PSNR dB | dtraced setting | dtraced s | dtraced PSNR dB | POV / dtraced | target | |"
  echo "|--:|---|---|--:|--:|---|--:|--:|--:|--:|---|"
  for t in $THREADS; do
    [ "$t" -le "$cores" ] || continue
    # Without antialiasing.
    ds=() ps=()
    for run in $(seq "$RUNS"); do
      ds+=("$(dtraced_render "$json" "$dir/dtraced-1spp.png" "$t" -s 1)")
      ps+=("$(pov_render "$pov" "$dir/povray-noaa.png" "$t" -A)")
    done
    d=$(median "${ds[@]}") p=$(median "${ps[@]}") r=$(ratio "$(median "${ps[@]}")" "$(median "${ds[@]}")")
    echo "| $t | no AA | -A | $p | $(psnr "$dir/povray-noaa.png" "$pref") | -s 1 | $d | $(psnr "$dir/dtraced-1spp.png" "$dref") | $r | 3 | $(verdict "$r" 3) |"
    summary+=("$name T=$t no AA: $r ($(verdict "$r" 3))")
    [ "$t" = "$top" ] && html_pair "$name, no antialiasing" "dtraced -s 1" "$dir/dtraced-1spp.png" "POV-Ray -A" "$dir/povray-noaa.png"

    # To equal error with antialiasing.
    for aa in 0.3 0.1; do
      ps=()
      for run in $(seq "$RUNS"); do ps+=("$(pov_render "$pov" "$dir/povray-aa$aa.png" "$t" +A"$aa" +AM1 +R3)"); done
      p=$(median "${ps[@]}")
      pp=$(psnr "$dir/povray-aa$aa.png" "$pref")
      # The cheapest ladder setting at least as accurate, by rays per pixel (a count, so load on
      # the machine cannot change which one is picked), then timed RUNS times.
      best=
      for i in "${!ladder[@]}"; do
        awk -v a="${ladder_psnr[$i]}" -v b="$pp" 'BEGIN { exit !(a >= b) }' || continue
        if [ -z "$best" ] || awk -v a="${ladder_rays[$i]}" -v b="${ladder_rays[$best]}" 'BEGIN { exit !(a < b) }'; then best=$i; fi
      done
      if [ -z "$best" ]; then
        echo "| $t | equal error | +A$aa +R3 | $p | $pp | (no ladder setting reaches it) | | | | 2 | MISSED |"
        summary+=("$name T=$t +A$aa: no dtraced setting reached $pp dB (MISSED)")
        continue
      fi
      read -r -a args <<<"${ladder[$best]}"
      ds=()
      for run in $(seq "$RUNS"); do ds+=("$(dtraced_render "$json" "$dir/dtraced-ladder-$best.png" "$t" "${args[@]}")"); done
      d=$(median "${ds[@]}") r=$(ratio "$p" "$(median "${ds[@]}")")
      echo "| $t | equal error | +A$aa +R3 | $p | $pp | ${ladder[$best]} | $d | ${ladder_psnr[$best]} | $r | 2 | $(verdict "$r" 2) |"
      summary+=("$name T=$t +A$aa: $r ($(verdict "$r" 2))")
      [ "$t" = "$top" ] && html_pair "$name, equal error, POV-Ray +A$aa +R3" "dtraced ${ladder[$best]} ($d s, ${ladder_psnr[$best]} dB)" \
        "$dir/dtraced-ladder-$best.png" "POV-Ray +A$aa +R3 ($p s, $pp dB)" "$dir/povray-aa$aa.png"
    done
  done
  echo
  # The reference's own noise is the 1-spp noise over REF_SPP: errors near this floor are not measurable.
  echo "dtraced reference noise floor: about $(awk -v p="$(psnr "$dir/dtraced-1spp.png" "$dref")" -v n="$REF_SPP" 'BEGIN { printf "%.1f", p + 10 * log(n) / log(10) }') dB PSNR"
  echo "dtraced ladder at $top threads (PSNR against its own reference):"
  for i in "${!ladder[@]}"; do echo "  ${ladder[$i]}: ${ladder_psnr[$i]} dB (${ladder_cost[$i]})"; done
done
echo
echo "summary (POV-Ray time / dtraced time; targets: 3 without AA, 2 at equal error):"
printf '  %s\n' "${summary[@]}"
echo "images side by side: $html"
echo "load average now $(cut -d' ' -f1-3 /proc/loadavg)"
