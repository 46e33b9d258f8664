"""hapticproxy.experiments"""
