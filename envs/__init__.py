"""Simulator adapters and scripted experts, shared by explore and evaluate."""
