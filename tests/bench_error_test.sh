#!/bin/bash
# `dtraced bench error` on small scenes: the CSV's columns and rows, the closed-form and the
# cached Monte Carlo reference, the plot, and clear errors. Needs $DTRACED and $SCENES.
set -u
T=$(mktemp -d)
trap 'rm -rf "$T"' EXIT
failures=0
check() {  # check DESCRIPTION COMMAND...
  local what=$1
  shift
  if "$@"; then echo "ok   $what"; else echo "FAIL $what"; failures=$((failures + 1)); fi
}

# 1. A scene with a closed form: one diffuse plane under point, sphere and rect lights.
"$DTRACED" bench error "$SCENES/lit_plane.json" --width 32 --height 24 --max-spp 8 --targets 0.1 0.05 \
  --min-samples 2 --repeats 1 --csv "$T/a.csv" --plot "$T/a.svg" >"$T/a.out" 2>"$T/a.err"
check "closed-form run exits 0" test $? -eq 0
check "the reference is the closed form" grep -q "reference: closed form" "$T/a.out"
check "the slope line is printed" grep -q "log-log slope" "$T/a.out"
check "the specialised path renders the same bits" grep -q "same bits: yes" "$T/a.out"
check "the CSV header names every column" test "$(head -1 "$T/a.csv")" = \
  "scene,isa,kind,target,spp,seconds,mrays_per_s,mse,rel_mse,psnr_db,max_abs,nonfinite,efficiency,ref_noise,rays_per_pixel,branch_cutoff"
check "uniform rows at 1, 2, 4, 8 spp" test "$(awk -F, '$3=="uniform"{printf "%d ", $5}' "$T/a.csv")" = "1 2 4 8 "
check "two adaptive rows, one per target" test "$(awk -F, '$3=="adaptive"{printf "%s ", $4}' "$T/a.csv")" = "0.1 0.05 "
check "one cut-off row at 1/255 and 8 spp" test "$(awk -F, '$3=="cutoff"{printf "%s %d ", $16, $5}' "$T/a.csv")" = "0.00392157 8 "
check "the cut-off row is compared with the uniform row" grep -q "branch cut-off 0.00392157 at 8 spp" "$T/a.out"
check "no NaN or Inf in any row" test "$(awk -F, 'NR>1 && $12!=0' "$T/a.csv" | wc -l)" -eq 0
check "uniform relMSE falls with every doubling" \
  awk -F, 'NR>1 && $3=="uniform" { if (n++ && $9 >= last) bad=1; last=$9 } END { exit bad || n != 4 }' "$T/a.csv"
check "efficiency is 1 / (relMSE x seconds)" \
  awk -F, 'NR>1 { e = 1 / ($9 * $6); if ($13 < e * 0.999 || $13 > e * 1.001) bad=1 } END { exit bad }' "$T/a.csv"
check "a closed form has no reference noise" test "$(awk -F, 'NR>1 && $14!=0' "$T/a.csv" | wc -l)" -eq 0
check "adaptive rows take fewer samples than the cap" \
  awk -F, '$3=="adaptive" { if ($5 >= 8 || $5 < 2) bad=1 } END { exit bad }' "$T/a.csv"
check "the SVG plot is written" grep -q "<svg" "$T/a.svg"

# 2. No closed form: a Monte Carlo reference, rendered once and then read from the cache.
mkdir "$T/cache"
run_soft() {
  "$DTRACED" bench error "$SCENES/soft_shadows.json" --width 24 --height 18 --max-spp 4 --targets 0.2 \
    --min-samples 1 --reference-spp 64 --repeats 1 --cache-dir "$T/cache" --csv "$T/b.csv" --plot "$T/b.png" \
    >"$T/b$1.out" 2>"$T/b$1.err"
}
run_soft 1
check "Monte Carlo reference run exits 0" test $? -eq 0
check "first run renders the reference" grep -q "rendering the reference at 64 spp" "$T/b1.err"
check "the reference is cached beside the digest" test "$(ls "$T/cache" | grep -c '^soft_shadows\.ref-[0-9a-f]\{16\}\.pfm$')" -eq 1
check "its variance is cached too" test "$(ls "$T/cache" | grep -c '\.var\.pfm$')" -eq 1
check "the reference's noise is estimated" test "$(awk -F, 'NR>1 && $14>0' "$T/b.csv" | wc -l)" -eq 5
cp "$T/b.csv" "$T/b1.csv"
run_soft 2
check "second run exits 0" test $? -eq 0
check "second run reads the cache" grep -q "cached $T/cache/soft_shadows.ref-" "$T/b2.out"
check "second run does not render it" test "$(grep -c "rendering the reference" "$T/b2.err")" -eq 0
check "same reference, same errors" test "$(cut -d, -f8,9,11 "$T/b1.csv")" = "$(cut -d, -f8,9,11 "$T/b.csv")"
check "the PNG plot is written" test "$(head -c 4 "$T/b.png" | od -An -c | tr -d ' ')" = "211PNG"
# A different reference sample count is a different file.
"$DTRACED" bench error "$SCENES/soft_shadows.json" --width 24 --height 18 --max-spp 2 --no-adaptive \
  --reference-spp 32 --repeats 1 --cache-dir "$T/cache" --csv "$T/c.csv" --no-plot >/dev/null 2>&1
check "another reference spp gets its own cache entry" test "$(ls "$T/cache" | grep -c '\.ref-[0-9a-f]*\.pfm$')" -eq 2

# 3. Errors name what is wrong and exit 1.
"$DTRACED" bench error "$T/missing.json" --no-plot >/dev/null 2>"$T/e1"
check "a missing scene exits 1" test $? -eq 1
check "and names the file" grep -q "missing.json" "$T/e1"
"$DTRACED" bench error "$SCENES/lit_plane.json" --width 8 --height 6 --max-spp 2 --no-adaptive --repeats 1 \
  --csv "$T/d.csv" --plot "$T/d.gif" >/dev/null 2>"$T/e2"
check "an unknown plot format exits 1" test $? -eq 1
check "and names the plot" grep -q "d.gif" "$T/e2"
"$DTRACED" bench error "$SCENES/lit_plane.json" --max-spp 8 --min-samples 8 --no-plot >/dev/null 2>"$T/e3"
check "--min-samples at the cap exits 1" test $? -eq 1
check "and says why" grep -q "min-samples" "$T/e3"

"$DTRACED" bench error "$SCENES/soft_shadows.json" --max-spp 16 --reference-spp 16 --no-plot >/dev/null 2>"$T/e4"
check "a reference no better than the rows exits 1" test $? -eq 1
check "and says why" grep -q "reference-spp 16 must be above --max-spp 16" "$T/e4"

echo "$failures failure(s)"
test "$failures" -eq 0
