"""Configs, task records, Arrow table schemas and the on-disk layout. Imports nothing of ours."""
