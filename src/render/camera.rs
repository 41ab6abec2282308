//! Cameras looking down on the cloth: orthographic (default) or pinhole, with in-plane rotation
//! and tilt. World units: pitch = 10; the cloth's mid-plane is z = 0, its front faces +z.

use crate::scene::{CameraSpec, Projection};
use glam::{Quat, Vec3};

/// A camera ready to generate rays for a `width × height` image.
#[derive(Clone, Debug)]
pub struct Camera {
    projection: Projection,
    centre: Vec3,
    right: Vec3,
    up: Vec3,
    forward: Vec3,
    half_w: f32,
    half_h: f32,
    width: u32,
    height: u32,
    dist: f32,
}

impl Camera {
    /// Build from the scene spec; `tile_x`, `tile_y` are the pattern repeat sizes; `z_top` bounds the
    /// cloth from above.
    pub fn new(spec: &CameraSpec, width: u32, height: u32, tile_x: f32, tile_y: f32, z_top: f32) -> Self {
        let half_w = 0.5 * spec.tiles * tile_x;
        let half_h = half_w * height as f32 / width as f32;
        let rot = Quat::from_rotation_z(spec.rotation_deg.to_radians());
        let right0 = rot * Vec3::X;
        let tilt = Quat::from_axis_angle(right0, spec.tilt_deg.to_radians());
        let forward = (tilt * rot * -Vec3::Z).normalize();
        let up = (tilt * rot * Vec3::Y).normalize();
        let right = right0;
        let centre = Vec3::new(spec.offset[0] * tile_x, spec.offset[1] * tile_y, 0.0);
        let dist = match spec.projection {
            Projection::Orthographic => (z_top + 1.0) / (-forward.z).max(0.2),
            Projection::Perspective => half_h / (0.5 * spec.fov_deg.to_radians()).tan(),
        };
        Camera { projection: spec.projection, centre, right, up, forward, half_w, half_h, width, height, dist }
    }

    /// Ray (origin, unit direction) through image position `(px, py)` in pixels (continuous).
    pub fn ray(&self, px: f32, py: f32) -> (Vec3, Vec3) {
        let u = (px / self.width as f32) * 2.0 - 1.0;
        let v = 1.0 - (py / self.height as f32) * 2.0;
        match self.projection {
            Projection::Orthographic => {
                let on_plane = self.centre + self.right * (u * self.half_w) + self.up * (v * self.half_h);
                // Start every ray above the cloth slab, whatever the tilt lifts or lowers its image
                // point by (a fixed distance would start rays under the cloth at the frame's edge).
                let t = (self.dist * (-self.forward.z).max(0.2) - on_plane.z) / (-self.forward.z).max(0.2);
                (on_plane - self.forward * t, self.forward)
            }
            Projection::Perspective => {
                let eye = self.centre - self.forward * self.dist;
                let target = self.centre + self.right * (u * self.half_w) + self.up * (v * self.half_h);
                (eye, (target - eye).normalize())
            }
        }
    }

    /// World length that one pixel spans on the cloth's mid-plane at the view centre (the
    /// orthographic pixel size; for the pinhole, its size at the centre's distance). Tilt stretches
    /// it along one axis; the ply mapping accounts for that through the view's foreshortening.
    pub fn pixel_footprint(&self) -> f32 {
        2.0 * self.half_w / self.width as f32
    }

    /// Image size.
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ortho_top_down_frames_the_requested_tiles() {
        let spec = CameraSpec { tiles: 2.0, ..Default::default() };
        let c = Camera::new(&spec, 100, 50, 20.0, 20.0, 8.0);
        let (o0, d) = c.ray(0.0, 25.0);
        let (o1, _) = c.ray(100.0, 25.0);
        assert!((d - -Vec3::Z).length() < 1e-6);
        assert!(((o1.x - o0.x) - 40.0).abs() < 1e-4);
        let spec = CameraSpec { projection: Projection::Perspective, tilt_deg: 20.0, ..Default::default() };
        let c = Camera::new(&spec, 64, 64, 20.0, 20.0, 8.0);
        let (o, d) = c.ray(32.0, 32.0);
        let hit = o + d * (-o.z / d.z);
        assert!(hit.truncate().length() < 1e-3, "centre ray lands at {hit}");
        assert!(d.z < 0.0);
        // A tilted orthographic view starts every ray above the cloth (z_top = 8).
        let spec = CameraSpec { tilt_deg: 30.0, tiles: 4.0, ..Default::default() };
        let c = Camera::new(&spec, 64, 64, 20.0, 20.0, 8.0);
        for (px, py) in [(0.0, 0.0), (64.0, 64.0), (0.0, 64.0), (64.0, 0.0)] {
            assert!(c.ray(px, py).0.z > 8.0);
        }
    }
}
