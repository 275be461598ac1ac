"""mjx_morph.ppo"""
