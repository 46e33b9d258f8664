"""hapticproxy.clients"""
