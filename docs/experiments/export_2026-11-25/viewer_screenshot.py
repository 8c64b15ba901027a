"""Screenshot of `avatarctl view` on a fitted project in headless Chromium: python viewer_screenshot.py RES WAIT_S OUT.png
(run from the repository root with PYTHONPATH=.:tests; reads /tmp/P10)."""
import sys, time, json
sys.path.insert(0, "tests")
from fixtures.browser import Browser, free_port
from avatarctl.stages.view import ViewConfig, prepare
from avatarctl.viewer.server import ViewerServer
import cv2
setup = prepare("/tmp/P10", ViewConfig(device="cpu"))
server = ViewerServer(setup.session, setup.initial, port=free_port(), resolution=int(sys.argv[1]))
print("url", server.url, flush=True)
b = Browser(800, 600)
b.open(server.url)
t0 = time.time(); shown = []
while time.time() - t0 < float(sys.argv[2]):
    time.sleep(5)
    rs = list(server._renderers.values())
    if rs and any(full for _, full, _ in rs[0].frames_shown):
        time.sleep(2)
        break
img = b.screenshot()
cv2.imwrite(sys.argv[3], img[..., ::-1])
rs = list(server._renderers.values())
print(json.dumps({"frames_shown": rs[0].frames_shown if rs else None, "waited_s": time.time() - t0}), flush=True)
b.close(); server.stop(); print("stopped")
