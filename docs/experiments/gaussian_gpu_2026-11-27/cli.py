"""Scratch (not product): the avatarctl CLI with the frozen body (no anny cache on the GPU machine)."""
import os, sys
sys.path.insert(0, os.getcwd()); sys.path.insert(0, os.path.join(os.getcwd(), ".gpu"))
import frozen
frozen.patch(os.path.join(os.getcwd(), ".gpu", "body_small.npz"))
from avatarctl.cli.app import main
sys.argv[0] = "avatarctl"
main()
