"""``sage bench qp|env|scripted|learner|system``: benchmarks that print JSON
with ratios measured in the same run."""
