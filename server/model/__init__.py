"""hapticproxy.server.model"""
