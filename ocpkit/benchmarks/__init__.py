"""Benchmarks behind `ocpkit bench …`: they print medians and ratios measured side by side in one run."""
