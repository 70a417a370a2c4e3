#!/usr/bin/env bash
# Regenerate docs/images/rerun_view.png: a screenshot of the Rerun web viewer
# showing a demo recording, taken on a headless machine (no display, no GPU).
#
# Requirements: the project venv active (`ar-anchor`, `rerun`, `python` on PATH)
# and Debian's Chromium and pngquant (`apt-get install chromium pngquant`).
# WebGL is provided by Chromium's SwiftShader software rasterizer.
#
# usage: docs/rerun_screenshot.sh [OUT_PNG]
set -euo pipefail

OUT=${1:-"$(cd "$(dirname "$0")" && pwd)/images/rerun_view.png"}
WORK=$(mktemp -d /tmp/rerun_shot.XXXXXX)
GRPC_PORT=${GRPC_PORT:-9876}
WEB_PORT=${WEB_PORT:-9090}
WAIT_S=${WAIT_S:-35}        # real seconds to let the wasm viewer load + ingest
SIZE=${SIZE:-1600x900}

# 1. Make a recording (writes $WORK/run/recording.rrd with the default blueprint).
ar-anchor -q demo --frames 120 --out "$WORK/run"

# 2. Serve it with Rerun's web viewer, bound to localhost only. `rerun` is a
#    Python wrapper around the real binary, so run it in its own process group
#    (setsid) and stop the whole group at the end.
for port in "$GRPC_PORT" "$WEB_PORT"; do
    if (exec 3<>"/dev/tcp/127.0.0.1/$port") 2>/dev/null; then
        echo "port $port is already in use (set GRPC_PORT / WEB_PORT)" >&2; exit 1
    fi
done
setsid rerun --serve-web --bind 127.0.0.1 --port "$GRPC_PORT" --web-viewer-port "$WEB_PORT" \
    "$WORK/run/recording.rrd" >"$WORK/rerun.log" 2>&1 &
RERUN_PID=$!
trap 'kill -- -"$RERUN_PID" 2>/dev/null || true' EXIT
until (exec 3<>"/dev/tcp/127.0.0.1/$WEB_PORT") 2>/dev/null; do
    kill -0 "$RERUN_PID" 2>/dev/null || { cat "$WORK/rerun.log" >&2; exit 1; }
    sleep 0.5
done

# 3. Headless Chromium, driven over the DevTools protocol (pipe transport, stdlib
#    only) so that we wait in *real* time: --screenshot/--virtual-time-budget fire
#    before the wasm viewer has started.
cat >"$WORK/cdp_shot.py" <<'PY'
import base64, json, os, subprocess, sys, tempfile, time

url, out, wait, size = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4]
w, h = (int(v) for v in size.split("x"))
r_cmd, w_cmd = os.pipe()   # commands  -> chromium fd 3
r_res, w_res = os.pipe()   # responses <- chromium fd 4
args = ["chromium", "--headless", "--no-sandbox", "--disable-gpu",
        "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
        "--disable-background-networking", "--disable-component-update",
        "--disable-sync", "--no-first-run",
        "--user-data-dir=" + tempfile.mkdtemp(prefix="chromium_"),
        f"--window-size={w},{h}", "--hide-scrollbars",
        "--remote-debugging-pipe", "about:blank"]

def fds():
    os.dup2(r_cmd, 3)
    os.dup2(w_res, 4)

proc = subprocess.Popen(args, pass_fds=(3, 4), preexec_fn=fds,
                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
os.close(r_cmd); os.close(w_res)
rfile = os.fdopen(r_res, "rb", buffering=0)
buf, n = b"", 0

def send(method, params=None, session=None):
    global buf, n
    n += 1
    msg = {"id": n, "method": method, "params": params or {}}
    if session:
        msg["sessionId"] = session
    os.write(w_cmd, json.dumps(msg).encode() + b"\0")
    while True:
        while b"\0" not in buf:
            chunk = rfile.read(1 << 20)
            if not chunk:
                raise RuntimeError("chromium exited")
            buf += chunk
        raw, buf = buf.split(b"\0", 1)
        reply = json.loads(raw)
        if reply.get("id") == n:
            if "error" in reply:
                raise RuntimeError(f"{method}: {reply['error']}")
            return reply.get("result", {})

try:
    tid = send("Target.createTarget", {"url": "about:blank"})["targetId"]
    s = send("Target.attachToTarget", {"targetId": tid, "flatten": True})["sessionId"]
    send("Emulation.setDeviceMetricsOverride",
         {"width": w, "height": h, "deviceScaleFactor": 1, "mobile": False}, session=s)
    send("Emulation.setEmulatedMedia",   # Rerun follows the system theme; use dark
         {"features": [{"name": "prefers-color-scheme", "value": "dark"}]}, session=s)
    send("Page.navigate", {"url": url}, session=s)
    time.sleep(wait)
    data = send("Page.captureScreenshot", {"format": "png"}, session=s)["data"]
    with open(out, "wb") as f:
        f.write(base64.b64decode(data))
finally:
    try:
        send("Browser.close")
    except Exception:
        pass
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
PY

python "$WORK/cdp_shot.py" \
    "http://127.0.0.1:$WEB_PORT/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A$GRPC_PORT%2Fproxy" \
    "$WORK/raw.png" "$WAIT_S" "$SIZE"

# 4. Shrink: 256-colour palette PNG via pngquant (`apt-get install pngquant`),
#    ~150-200 KB at 1600x900.
mkdir -p "$(dirname "$OUT")"
pngquant --quality=70-95 --speed 1 --strip --force --output "$OUT" "$WORK/raw.png"
echo "wrote $OUT ($(stat -c %s "$OUT") bytes)"
