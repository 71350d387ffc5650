"""adalio.sim"""
