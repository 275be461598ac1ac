"""mjx_morph.nets"""
