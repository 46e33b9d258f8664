"""hapticproxy.cli"""
