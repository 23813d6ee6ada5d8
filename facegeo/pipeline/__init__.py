"""Pipeline: the benchmark registry (:mod:`.bench`) and the benchmarks of each stage
(:mod:`.benchmarks`)."""
