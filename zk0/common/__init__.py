"""What every layer uses: one-sentence errors, the cache root, the machine's CPUs, named generated assets."""
