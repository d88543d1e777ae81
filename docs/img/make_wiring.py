"""Draw `trigger-wiring.png`: how the trigger box (an Arduino) reaches three cameras and two
event sensors (docs/hardware.md, "The trigger box: build, wire, flash, check").

Run from the repository root: `python docs/img/make_wiring.py`. Needs only OpenCV and numpy
(`pip install 'rigd[frames]'`); the drawing is deterministic, so the PNG only changes when
this script does. OpenCV's Hershey fonts have no Greek letters: the picture writes "Ohm" and "us".
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

OUT = Path(__file__).resolve().parent / "trigger-wiring.png"
W, H = 1500, 1060
MAX_BYTES = 200_000

WHITE = (255, 255, 255)
BLACK = (20, 20, 20)
GREY = (120, 120, 120)
LIGHT = (235, 235, 235)
RED = (30, 30, 200)  # BGR: 5 V trigger
ORANGE = (0, 130, 230)  # 3.3 V trigger
BLUE = (190, 110, 20)  # USB
GREEN = (60, 140, 40)  # ground
BOX_BOARD = (225, 240, 225)
BOX_IC = (240, 232, 215)
BOX_CAM = (245, 235, 225)
BOX_EV = (225, 235, 250)
BOX_HOST = (235, 235, 235)

FONT = cv2.FONT_HERSHEY_SIMPLEX
BOLD = cv2.FONT_HERSHEY_DUPLEX


def text(
    img: np.ndarray, s: str, x: int, y: int, scale: float = 0.55, color=BLACK, bold: bool = False
) -> None:
    cv2.putText(img, s, (x, y), BOLD if bold else FONT, scale, color, 1, cv2.LINE_AA)


def box(img: np.ndarray, x0: int, y0: int, x1: int, y1: int, fill, title: str, lines: list[str]) -> None:
    cv2.rectangle(img, (x0, y0), (x1, y1), fill, -1)
    cv2.rectangle(img, (x0, y0), (x1, y1), BLACK, 2, cv2.LINE_AA)
    text(img, title, x0 + 10, y0 + 24, 0.6, bold=True)
    for i, line in enumerate(lines):
        text(img, line, x0 + 10, y0 + 48 + 21 * i, 0.5)


def dashed_rect(img: np.ndarray, x0: int, y0: int, x1: int, y1: int, color=GREY, dash: int = 12) -> None:
    for x in range(x0, x1, 2 * dash):
        cv2.line(img, (x, y0), (min(x + dash, x1), y0), color, 2)
        cv2.line(img, (x, y1), (min(x + dash, x1), y1), color, 2)
    for y in range(y0, y1, 2 * dash):
        cv2.line(img, (x0, y), (x0, min(y + dash, y1)), color, 2)
        cv2.line(img, (x1, y), (x1, min(y + dash, y1)), color, 2)


def wire(img: np.ndarray, pts: list[tuple[int, int]], color, width: int = 3) -> None:
    cv2.polylines(img, [np.array(pts, np.int32)], False, color, width, cv2.LINE_AA)


def resistor(img: np.ndarray, x: int, y: int, label: str, color) -> None:
    """A horizontal resistor (zig-zag) from x to x + 50 on the line y, labelled above."""
    pts = [(x, y), (x + 8, y)]
    for i in range(6):
        pts.append((x + 12 + 6 * i, y - 7 if i % 2 == 0 else y + 7))
    pts += [(x + 46, y), (x + 50, y)]
    wire(img, pts, color, 2)
    text(img, label, x - 2, y - 12, 0.45)


def dot(img: np.ndarray, x: int, y: int, color) -> None:
    cv2.circle(img, (x, y), 5, color, -1, cv2.LINE_AA)


def connector(img: np.ndarray, x: int, y: int, label: str) -> None:
    """A panel connector on the enclosure wall at (x, y)."""
    cv2.circle(img, (x, y), 9, WHITE, -1, cv2.LINE_AA)
    cv2.circle(img, (x, y), 9, BLACK, 2, cv2.LINE_AA)
    text(img, label, x - 14, y - 16, 0.45, bold=True)


def draw() -> np.ndarray:
    img = np.full((H, W, 3), 255, np.uint8)
    text(img, "rigd trigger box: wiring", 20, 36, 0.9, bold=True)
    text(
        img,
        "One trigger pin, buffered once per device. Uno/Nano: D9 (PB1, OC1A). Mega 2560: D11 (PB5, OC1A). "
        "Idle low, active-high pulse.",
        20,
        64,
        0.5,
    )

    # The enclosure.
    ex0, ey0, ex1, ey1 = 270, 95, 880, 1000
    dashed_rect(img, ex0, ey0, ex1, ey1)
    text(img, "trigger box enclosure", ex0 + 10, ey0 + 22, 0.5, GREY)

    # Host.
    box(
        img,
        20,
        430,
        230,
        590,
        BOX_HOST,
        "Host PC (rigd)",
        [
            "/dev/ttyACM0: Uno, Mega",
            "/dev/ttyUSB0: Nano clone",
            "config [trigger] spec =",
            "serial:///dev/ttyACM0",
            "  ?baud=1000000",
        ],
    )

    # Arduino.
    ax0, ay0, ax1, ay1 = 300, 400, 520, 640
    box(
        img,
        ax0,
        ay0,
        ax1,
        ay1,
        BOX_BOARD,
        "Arduino",
        [
            "Uno R3 / Nano",
            "(ATmega328P, 16 MHz)",
            "or Mega 2560",
            "",
            "D13 LED: lit while",
            "a run is going",
            "D8 (ICP1): reserved",
        ],
    )
    # Board pins on its right edge.
    pins = {"D9 TRIG": 440, "5V": 480, "3V3": 520}
    for name, y in pins.items():
        cv2.circle(img, (ax1, y), 5, BLACK, -1, cv2.LINE_AA)
        text(img, name, ax1 - 78, y + 5, 0.5, bold=True)

    # USB host <-> Arduino.
    wire(img, [(230, 510), (300, 510)], BLUE, 5)
    text(img, "USB", 244, 500, 0.5, BLUE, bold=True)

    # U1: 5 V buffer for the cameras.
    ux0, uy0, ux1, uy1 = 600, 130, 720, 400
    cv2.rectangle(img, (ux0, uy0), (ux1, uy1), BOX_IC, -1)
    cv2.rectangle(img, (ux0, uy0), (ux1, uy1), BLACK, 2, cv2.LINE_AA)
    text(img, "U1", ux0 + 8, uy0 + 22, 0.6, bold=True)
    text(img, "74ACT244", ux0 + 8, uy0 + 44, 0.5)
    text(img, "VCC = 5 V", ux0 + 8, uy0 + 64, 0.5)
    text(img, "100 nF at VCC", ux0 + 8, uy0 + 84, 0.42)
    text(img, "unused inputs", ux0 + 8, uy1 - 34, 0.42)
    text(img, "to GND, /OE to GND", ux0 + 8, uy1 - 16, 0.38)

    # U2: 3.3 V buffer for the event sensors.
    vx0, vy0, vx1, vy1 = 600, 690, 720, 930
    cv2.rectangle(img, (vx0, vy0), (vx1, vy1), BOX_IC, -1)
    cv2.rectangle(img, (vx0, vy0), (vx1, vy1), BLACK, 2, cv2.LINE_AA)
    text(img, "U2", vx0 + 8, vy0 + 22, 0.6, bold=True)
    text(img, "74LVC125A", vx0 + 8, vy0 + 44, 0.5)
    text(img, "VCC = 3.3 V", vx0 + 8, vy0 + 64, 0.5)
    text(img, "inputs take 5 V", vx0 + 8, vy0 + 84, 0.42)
    text(img, "100 nF at VCC", vx0 + 8, vy0 + 104, 0.42)
    text(img, "/OE to GND", vx0 + 8, vy1 - 16, 0.42)

    # Trigger net from D9 to both ICs' inputs.
    bus_x = 560
    wire(img, [(ax1, 440), (bus_x, 440)], RED)
    wire(img, [(bus_x, 190), (bus_x, 850)], RED)
    dot(img, bus_x, 440, RED)
    cam_rows = [190, 270, 350]
    ev_rows = [770, 850]
    for y in cam_rows:
        wire(img, [(bus_x, y), (ux0, y)], RED)
        dot(img, bus_x, y, RED)
    for y in ev_rows:
        wire(img, [(bus_x, y), (vx0, y)], RED)
        dot(img, bus_x, y, RED)
    text(img, "5 V", bus_x + 6, 600, 0.5, RED, bold=True)

    # Supplies: 5V pin to U1 VCC, 3V3 pin to U2 VCC.
    wire(img, [(ax1, 480), (540, 480), (540, 110), (660, 110), (660, uy0)], (90, 90, 90), 2)
    text(img, "5V", 668, 122, 0.45, bold=True)
    wire(img, [(ax1, 520), (540, 520), (540, 670), (660, 670), (660, vy0)], (90, 90, 90), 2)
    text(img, "3.3 V (Uno 3V3 pin or LDO)", 545, 664, 0.42, bold=True)

    # Outputs with series resistors to the panel connectors.
    wall = ex1
    for i, y in enumerate(cam_rows):
        wire(img, [(ux1, y), (760, y)], RED)
        resistor(img, 760, y, "R 47 Ohm", RED)
        wire(img, [(810, y), (wall, y)], RED)
        connector(img, wall, y, f"J{i + 1}")
    for i, y in enumerate(ev_rows):
        wire(img, [(vx1, y), (760, y)], ORANGE)
        resistor(img, 760, y, "R 33 Ohm", ORANGE)
        wire(img, [(810, y), (wall, y)], ORANGE)
        connector(img, wall, y, f"J{i + 4}")

    # Ground: one star point; a rail inside the wall takes every connector's return to it.
    sx, sy, rail_x = 410, 960, 845
    wire(img, [(sx, ay1), (sx, sy), (rail_x, sy), (rail_x, cam_rows[0] + 9)], GREEN, 2)
    cv2.circle(img, (sx, ay1), 5, BLACK, -1, cv2.LINE_AA)
    text(img, "GND", sx - 18, ay1 - 10, 0.5, bold=True)
    for y in cam_rows + ev_rows:
        wire(img, [(rail_x, y + 9), (wall - 6, y + 9)], GREEN, 2)
        dot(img, rail_x, y + 9, GREEN)
    wire(img, [(700, uy1), (700, uy1 + 30), (rail_x, uy1 + 30)], GREEN, 2)
    dot(img, rail_x, uy1 + 30, GREEN)
    wire(img, [(700, vy1), (700, sy)], GREEN, 2)
    dot(img, 700, sy, GREEN)
    cv2.drawMarker(img, (sx, sy), GREEN, cv2.MARKER_STAR, 28, 3, cv2.LINE_AA)
    text(img, "star GND", sx - 118, sy - 6, 0.55, GREEN, bold=True)
    text(img, "(one point)", sx - 118, sy + 14, 0.45, GREEN)
    text(img, "GND rail: every", 748, 470, 0.42, GREEN)
    text(img, "connector's return", 748, 488, 0.42, GREEN)

    # Cameras.
    cam_specs = [
        ("Camera 0 (RGB)", "opto-isolated input"),
        ("Camera 1 (RGB)", "opto-isolated input"),
        ("Camera 2 (RGB)", "opto-isolated input"),
    ]
    cx0, cx1 = 1120, 1480
    for i, y in enumerate(cam_rows):
        top = y - 32
        box(img, cx0, top, cx1, top + 70, BOX_CAM, cam_specs[i][0], [cam_specs[i][1] + ": IN+ and opto GND"])
        wire(img, [(wall, y - 6), (cx0, y - 6)], RED, 3)
        wire(img, [(wall, y + 6), (cx0, y + 6)], BLACK, 2)
    text(img, "shielded twisted pair, a few m", 905, cam_rows[0] - 44, 0.5, bold=True)
    text(img, "(shield to GND at the box only)", 905, cam_rows[0] - 24, 0.45)
    text(img, "signal / opto GND", 925, cam_rows[2] + 34, 0.45)

    # Camera pin legend.
    lx, ly = 905, 420
    cv2.rectangle(img, (lx, ly), (cx1, ly + 150), LIGHT, -1)
    cv2.rectangle(img, (lx, ly), (cx1, ly + 150), BLACK, 1)
    text(
        img,
        "Camera I/O pins (signal / return); camera power GND stays unconnected",
        lx + 8,
        ly + 22,
        0.48,
        bold=True,
    )
    legend = [
        "Basler ace U/Classic: Hirose HR10 6-pin, pin 2 = Line 1 in, pin 5 = opto GND",
        "FLIR Blackfly S: HR10A-7R-6PB, pin 2 = OPTOIN (Line 0), pin 5 = Opto GND",
        "Alvium G1 (GigE): 10-pin TFM, pin 5 = GPI3 (isolated), pin 3 = OPTO-IN-GND",
        "Opto inputs: high > 2.2 V (Basler) / 2.6 V (FLIR) / 3.0 V (Alvium),",
        "draw 3.5-15 mA; U1 gives >= 3.76 V at 24 mA. Pulse width >= 100 us.",
    ]
    for i, s in enumerate(legend):
        text(img, s, lx + 8, ly + 48 + 21 * i, 0.45)

    # Event sensors.
    for i, y in enumerate(ev_rows):
        top = y - 32
        box(
            img,
            cx0,
            top,
            cx1,
            top + 70,
            BOX_EV,
            f"Event sensor {i} (EVK4)",
            ["Trigger In + GND: 3.3 V input assumed"],
        )
        wire(img, [(wall, y - 6), (cx0, y - 6)], ORANGE, 3)
        wire(img, [(wall, y + 6), (cx0, y + 6)], BLACK, 2)
    text(img, "coax (RG-174), <= 2 m", 905, ev_rows[0] - 44, 0.5, bold=True)
    text(img, "check the EVK4 manual's Trigger In", 905, ev_rows[1] + 52, 0.45)
    text(img, "levels and connector before use", 905, ev_rows[1] + 72, 0.45)

    # Event sensors' USB to the host: the ground loop.
    wire(img, [(cx1 - 60, ev_rows[1] + 38), (cx1 - 60, 1030)], BLUE, 4)
    wire(img, [(cx1, ev_rows[0]), (cx1 + 12, ev_rows[0]), (cx1 + 12, 1030), (125, 1030), (125, 590)], BLUE, 4)
    text(
        img,
        "EVK4 USB 3 to the host: EVK ground = host ground = box ground (keep the loop small)",
        300,
        1022,
        0.5,
        BLUE,
        bold=True,
    )
    text(img, "cameras' own data/power links not shown", 1120, 95, 0.45, GREY)

    # Colour legend.
    lx, ly = 20, 120
    items = [
        (RED, "5 V trigger"),
        (ORANGE, "3.3 V trigger"),
        (BLACK, "signal return"),
        (GREEN, "ground"),
        (BLUE, "USB"),
    ]
    text(img, "Legend", lx, ly, 0.55, bold=True)
    for i, (c, s) in enumerate(items):
        y = ly + 26 + 24 * i
        wire(img, [(lx, y - 5), (lx + 40, y - 5)], c, 4)
        text(img, s, lx + 50, y, 0.5)
    return img


def main() -> None:
    img = draw()
    ok, png = cv2.imencode(".png", img, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    assert ok
    if len(png) > MAX_BYTES:
        raise SystemExit(f"{OUT.name}: {len(png)} bytes, over {MAX_BYTES}")
    OUT.write_bytes(png.tobytes())
    print(f"wrote {OUT} ({len(png)} bytes, {W}x{H})")


if __name__ == "__main__":
    main()
