#!/bin/bash
# `dtraced bench error` on a small scene: the CSV columns, the rows and the plot.
echo "bench_error_test.sh: not written yet" >&2
exit 1
