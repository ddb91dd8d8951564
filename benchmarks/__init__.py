"""Speed and quality benchmarks against peers and physical limits (`make bench`)."""
