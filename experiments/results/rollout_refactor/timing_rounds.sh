R=$PWD
for i in 1 2 3; do
  for v in old new; do
    if [ $v = old ]; then cd $R/.carry/old; else cd $R; fi
    echo "== $v round $i"
    JAX_PLATFORMS=cpu taskset -c 0 python -m regrasp_mjx.evaluate --json --queries 200 2>/dev/null | head -c 1200; echo
  done
done
