"""Innovations of synthesis (design §10.8): the fitted innovation process, the bank of training
residuals and the draws.
"""
