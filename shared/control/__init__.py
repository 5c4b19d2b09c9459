"""shared.control"""
