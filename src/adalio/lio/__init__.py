"""adalio.lio"""
