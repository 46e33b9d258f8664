"""hapticproxy.server"""
