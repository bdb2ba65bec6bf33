// tecdar's soft fingertip, parametric (OpenSCAD; `make fingertip` renders every part).
//
// A silicone pad with the IMU's carrier cast in at a fixed depth under the contact face, on a rigid backing
// that screws to the gripper's finger. The pad is cast in two steps, as the TECDAR paper's fingertip is:
//   1. the face layer: silicone to `imu_depth` in the mould (the volume is echoed), cured;
//   2. the carrier laid chip-down on it through the locator's window (the locator lifted out), then the
//      rest of the silicone, and the backing pressed in until its plate sits on the mould's rim.
// The silicone does not bond to the printed backing: it flows into the backing's keying holes and locks
// there. The carrier is held by nothing rigid, so it turns with the silicone, not with the finger.
//
// Frame: the contact face at z = 0, the pad above it to z = pad_t, the backing above that; x along the finger,
// y across it (the cable leaves at +y). Millimetres.
//
// `part` selects the part: pad, carrier, mould, locator, backing_franka, backing_robotiq, assembly.
part = "assembly";

/* [Pad: the silicone] */
pad_l = 15;          // along the finger (the paper's fingertip: 15 x 10 mm)
pad_w = 10;          // across it
pad_t = 6;           // silicone, contact face to backing
pad_r = 1.5;         // corner radius
imu_depth = 2.0;     // silicone over the chip: contact face to the chip's face

/* [Carrier: the IMU on its board] */
carrier_l = 7.0;     // a 2.5 x 3 mm LGA-14 on its own small board; a breakout is bigger: measure yours
carrier_w = 6.0;
carrier_t = 1.6;     // board and chip
cable_w = 4.0;       // the cable's bundle or flat flex where it leaves the carrier
cable_t = 1.2;

/* [Backing: rigid, printed] */
back_t = 3.0;        // the boss that the silicone grips, inside the mould
key_d = 1.6;         // keying holes through the boss
plate_t = 3.0;       // the mount plate over the boss
clearance = 0.2;     // boss to mould wall, each side

/* [How the backing holds on: screws (the spacings below, unverified: measure your finger) or bonded (no holes:
   the plate's back face on the finger's flat gripping face with 1 mm acrylic foam tape, e.g. 3M VHB 4910; the
   tape adds compliance under the pad, so calibrate eta after mounting, as for any new pad)] */
mount = "screws";    // screws | bonded

/* [Mount on a Franka Hand finger: unverified, measure your finger] */
franka_plate_l = 34;
franka_plate_w = 20;
franka_hole_spacing = 26;   // two screws along x, outside the pad
franka_screw_d = 3.2;       // M3 clearance
franka_head_d = 6.0;

/* [Mount on a Robotiq 2F-85 finger, in place of its pad: unverified, measure your finger] */
robotiq_plate_l = 36;
robotiq_plate_w = 22;
robotiq_hole_spacing = 28;
robotiq_screw_d = 3.2;
robotiq_head_d = 6.0;

/* [Mould] */
wall = 3.0;
floor_t = 2.0;
pin_d = 2.5;         // registration pins of the mould, holes in the plate

$fn = 40;
eps = 0.01;

assert(imu_depth + carrier_t <= pad_t - 1.0, "the carrier needs 1 mm of silicone behind it: raise pad_t");
assert(carrier_l <= pad_l - 2 && carrier_w <= pad_w - 2, "the carrier needs 1 mm of silicone at each side");

module rounded_rect(l, w, h, r) {
    rr = min(r, l / 2 - eps, w / 2 - eps);
    linear_extrude(h) offset(r = rr) square([l - 2 * rr, w - 2 * rr], center = true);
}

// the cast silicone, with the carrier's cavity and the cable's channel to the backing
module pad() {
    difference() {
        rounded_rect(pad_l, pad_w, pad_t, pad_r);
        translate([0, 0, imu_depth]) carrier_envelope();
        cable_path(pad_t + eps);
    }
}

module carrier_envelope() {
    translate([-carrier_l / 2, -carrier_w / 2, 0]) cube([carrier_l, carrier_w, carrier_t]);
}

module carrier() {
    translate([0, 0, imu_depth]) color("darkgreen") difference() {
        carrier_envelope();
        translate([0, 0, -eps]) linear_extrude(0.8 + eps) square([3.0, 2.5], center = true);
    }
    translate([0, 0, imu_depth]) color("black") linear_extrude(0.8) square([3.0, 2.5], center = true);
}

// from the carrier's +x edge straight up through the pad and the backing
module cable_path(top) {
    translate([carrier_l / 2 - cable_t, -cable_w / 2, imu_depth + carrier_t / 2]) cube([cable_t + 0.4, cable_w, top]);
}

// the backing's boss, its keying holes and the cable's slot; the plate is the mount's
module boss() {
    difference() {
        translate([0, 0, pad_t]) rounded_rect(pad_l - 2 * clearance, pad_w - 2 * clearance, back_t, max(pad_r - clearance, 0.2));
        for (sx = [-1, 1]) for (sy = [-1, 1])
            translate([sx * (pad_l / 2 - 2.0), sy * (pad_w / 2 - 2.0), pad_t - eps]) cylinder(d = key_d, h = back_t + plate_t + 2 * eps);
        cable_path(pad_t + back_t + plate_t + 1);
    }
}

module backing(plate_l, plate_w, spacing, screw_d, head_d) {
    assert(mount == "bonded" || mount == "screws", "mount is screws or bonded");
    assert(mount == "bonded" || spacing / 2 - head_d / 2 >= pad_l / 2 + 0.5,
           "the screws' heads must clear the pad: widen the spacing");
    assert(mount == "bonded" || spacing / 2 + head_d / 2 <= plate_l / 2,
           "the screws' heads must lie on the plate: lengthen it");
    assert(plate_w / 2 >= pad_w / 2 + wall / 2 + 1 + pin_d, "the plate must reach the mould's pins: widen it");
    difference() {
        union() {
            boss();
            translate([0, 0, pad_t + back_t]) rounded_rect(plate_l, plate_w, plate_t, 2);
        }
        // two screws into the finger, outside the pad, their heads counterbored into the plate's pad side
        if (mount == "screws") for (sx = [-1, 1]) translate([sx * spacing / 2, 0, pad_t + back_t - eps]) {
            cylinder(d = screw_d, h = plate_t + 2 * eps);
            cylinder(d = head_d, h = plate_t / 2);
        }
        // the registration pins of the mould
        for (p = pin_positions()) translate([p[0], p[1], pad_t + back_t - eps]) cylinder(d = pin_d + 0.3, h = plate_t + 2 * eps);
        // the cable's slot through the plate, and its groove on the plate's top to the +y edge, clear of the
        // screws (on the x axis) and the pins (at -x)
        cable_path(pad_t + back_t + plate_t + 1);
        translate([slot_x() - cable_w / 2, 0, pad_t + back_t + plate_t - cable_t]) cube([cable_w, plate_w, cable_t + eps]);
    }
}

// on the mould's rim across the pad, clear of the screws along it and of the cable's groove
function pin_positions() = [[-4, -(pad_w / 2 + wall / 2 + 1)], [-4, pad_w / 2 + wall / 2 + 1]];
function slot_x() = carrier_l / 2 - cable_t + (cable_t + 0.4) / 2;

module mould() {
    outer_l = pad_l + 2 * wall + 6;
    outer_w = pad_w + 2 * wall + 4;
    difference() {
        translate([0, 0, -floor_t]) rounded_rect(outer_l, outer_w, floor_t + pad_t + back_t, 2);
        rounded_rect(pad_l, pad_w, pad_t + back_t + eps, pad_r);
    }
    for (p = pin_positions()) translate([p[0], p[1], pad_t + back_t - eps]) cylinder(d = pin_d, h = plate_t * 0.8);
}

// step 2's jig: sits on the mould's rim on the pins, a window that guides the carrier down onto the face layer
module locator() {
    outer_l = pad_l + 2 * wall + 6;
    outer_w = pad_w + 2 * wall + 4;
    tube_h = pad_t + back_t - (imu_depth + carrier_t);
    win_l = carrier_l + 0.4;
    win_w = carrier_w + 0.4;
    difference() {
        union() {
            translate([0, 0, pad_t + back_t]) rounded_rect(outer_l, outer_w, 2, 2);
            translate([0, 0, imu_depth + carrier_t]) rounded_rect(win_l + 1.6, win_w + 1.6, tube_h + eps, 0.5);
        }
        translate([0, 0, imu_depth]) rounded_rect(win_l, win_w, pad_t + back_t + 3, 0.2);
        for (p = pin_positions()) translate([p[0], p[1], pad_t + back_t - eps]) cylinder(d = pin_d + 0.3, h = 3);
    }
}

module franka() { backing(franka_plate_l, franka_plate_w, franka_hole_spacing, franka_screw_d, franka_head_d); }
module robotiq() { backing(robotiq_plate_l, robotiq_plate_w, robotiq_hole_spacing, robotiq_screw_d, robotiq_head_d); }

echo(str("step 1, the face layer: ", pad_l * pad_w * imu_depth / 1000, " mL; the whole pad: ",
         pad_l * pad_w * pad_t / 1000, " mL of silicone"));

if (part == "pad") pad();
else if (part == "carrier") carrier();
else if (part == "mould") mould();
else if (part == "locator") locator();
else if (part == "backing_franka") franka();
else if (part == "backing_robotiq") robotiq();
else {
    color("silver", 0.35) translate([0, 0, -14]) mould();
    color("orange", 0.8) pad();
    carrier();
    color("steelblue") translate([0, 0, 10]) franka();
}
