"""TEST FIXTURE: the two ends of a WebRTC stream, with aiortc (PyPI) in place of the real ones.

`send` stands in for Isaac Sim's stream on the GPU host: it answers an offer, from its host
addresses only (no ICE server of its own), and sends small video frames. `receive` stands in for a
browser outside the LAN: it offers to receive video with relay-only ICE through the TURN server it
is given, trusting the CA in SSL_CERT_FILE, and counts what arrives. The test runs each in a network
namespace of its choosing (nsenter) and carries the offer and the answer between them, one JSON line
each on standard output and input. Both print one JSON line of what they saw at the end.
`probe-udp` and `probe-tcp` say whether a datagram is answered or a connection opens from here.
"""

import argparse
import asyncio
import json
import socket
import sys

FRAMES = 30
WIDTH, HEIGHT = 320, 240


def say(obj):
    print(json.dumps(obj), flush=True)


async def read_line() -> dict:
    line = await asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline)
    if not line:
        raise SystemExit("no description came on standard input")
    return json.loads(line)


def nominated(pc) -> dict:
    """The candidate pair ICE settled on, as this end sees it."""
    transceiver = pc.getTransceivers()[0]
    ice = (transceiver.sender or transceiver.receiver).transport.transport
    pairs = list(ice._connection._nominated.values())  # aioice keeps no public accessor for it
    if not pairs:
        return {}
    pair = pairs[0]
    local, remote = pair.local_candidate, pair.remote_candidate
    return {"local": [local.type, local.host, local.port], "remote": [remote.type, remote.host, remote.port]}


async def send(timeout: float):
    from aiortc import RTCConfiguration, RTCPeerConnection, RTCSessionDescription, VideoStreamTrack
    from av import VideoFrame

    class Frames(VideoStreamTrack):
        shade = 0

        async def recv(self):
            pts, time_base = await self.next_timestamp()
            frame = VideoFrame(width=WIDTH, height=HEIGHT)
            self.shade = (self.shade + 8) % 256
            for plane in frame.planes:
                plane.update(bytes([self.shade]) * plane.buffer_size)
            frame.pts, frame.time_base = pts, time_base
            return frame

    pc = RTCPeerConnection(RTCConfiguration(iceServers=[]))
    pc.addTrack(Frames())
    offer = await read_line()
    await pc.setRemoteDescription(RTCSessionDescription(**offer))
    await pc.setLocalDescription(await pc.createAnswer())
    say({"sdp": pc.localDescription.sdp, "type": pc.localDescription.type})
    connected = asyncio.Event()
    pc.on("connectionstatechange", lambda: connected.set() if pc.connectionState == "connected" else None)
    try:
        await asyncio.wait_for(connected.wait(), timeout)
        seen = nominated(pc)
        # until the receiver has what it wants and says so (or goes)
        await asyncio.wait_for(asyncio.get_running_loop().run_in_executor(None, sys.stdin.readline), timeout)
        say({"state": pc.connectionState, "pair": seen})
    except asyncio.TimeoutError:
        say({"state": pc.connectionState, "pair": {}})
    finally:
        await pc.close()


async def receive(turn: dict, timeout: float):
    from aiortc import (
        RTCConfiguration,
        RTCIceServer,
        RTCIceTransportPolicy,
        RTCPeerConnection,
        RTCSessionDescription,
    )

    servers = [RTCIceServer(urls=s["urls"], username=s["username"], credential=s["credential"]) for s in turn]
    pc = RTCPeerConnection(RTCConfiguration(iceServers=servers, iceTransportPolicy=RTCIceTransportPolicy.RELAY))
    pc.addTransceiver("video", direction="recvonly")
    tracks = asyncio.Queue()
    pc.on("track", tracks.put_nowait)
    await pc.setLocalDescription(await pc.createOffer())
    candidates = [line.split()[7] for line in pc.localDescription.sdp.splitlines() if line.startswith("a=candidate:")]
    say({"sdp": pc.localDescription.sdp, "type": pc.localDescription.type})
    await pc.setRemoteDescription(RTCSessionDescription(**(await read_line())))
    frames, sizes = 0, set()
    try:
        track = await asyncio.wait_for(tracks.get(), timeout)
        while frames < FRAMES:
            frame = await asyncio.wait_for(track.recv(), timeout)
            frames += 1
            sizes.add((frame.width, frame.height))
    except Exception as e:  # a timeout or a closed track: what stopped it is part of the report
        error = f"{type(e).__name__}: {e}"
    else:
        error = None
    say(
        {
            "frames": frames,
            "sizes": sorted(sizes),
            "candidates": candidates,
            "pair": nominated(pc),
            "state": pc.connectionState,
            "error": error,
        }
    )
    await pc.close()


def probe_udp(host: str, port: int, timeout: float):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(timeout)
        try:
            s.sendto(b"probe", (host, port))
            data = s.recv(2048)
        except OSError as e:
            say({"answered": False, "why": f"{type(e).__name__}: {e}"})
        else:
            say({"answered": True, "data": data[:64].decode(errors="replace")})


def probe_tcp(host: str, port: int, timeout: float):
    try:
        socket.create_connection((host, port), timeout=timeout).close()
    except OSError as e:
        say({"connected": False, "why": f"{type(e).__name__}: {e}"})
    else:
        say({"connected": True})


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("role", choices=["send", "receive", "probe-udp", "probe-tcp"])
    parser.add_argument("--turn", help="the iceServers a login got from the front door, as JSON")
    parser.add_argument("--to", help="HOST:PORT for a probe")
    parser.add_argument("--timeout", type=float, default=30.0)
    args = parser.parse_args()
    if args.role == "send":
        asyncio.run(send(args.timeout))
    elif args.role == "receive":
        asyncio.run(receive(json.loads(args.turn), args.timeout))
    else:
        host, port = args.to.rsplit(":", 1)
        (probe_udp if args.role == "probe-udp" else probe_tcp)(host, int(port), min(args.timeout, 3.0))


if __name__ == "__main__":
    main()
