"""adalio.eval"""
