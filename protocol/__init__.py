"""hapticproxy.protocol"""
