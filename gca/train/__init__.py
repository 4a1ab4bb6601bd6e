"""gca.train"""
