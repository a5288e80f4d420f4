"""Offline tools: demonstration searches and rope-model studies, with their data.

Command line: ``flyknot-tools``. No runtime package imports this one.
"""
