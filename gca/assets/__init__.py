"""gca.assets"""
