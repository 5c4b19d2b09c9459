"""services.offline"""
