"""mjx_morph.eval"""
