"""The lab's own benchmarks: network architectures, training steps, training chunks."""
