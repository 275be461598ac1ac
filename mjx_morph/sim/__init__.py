"""mjx_morph.sim"""
