"""hapticproxy.benchmarks"""
