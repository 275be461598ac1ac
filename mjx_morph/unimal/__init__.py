"""mjx_morph.unimal"""
