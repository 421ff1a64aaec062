"""motorctl_emulators"""
