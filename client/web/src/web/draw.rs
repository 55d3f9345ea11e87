//! The canvas and the HUD: the map's pixels put once a frame, then the lines over them (cells waiting for their
//! expansion, the area of interest and its hysteresis band, the camera and its view, north, a scale).

use wasm_bindgen::{Clamped, JsCast, JsValue};
use web_sys::{CanvasRenderingContext2d, Document, HtmlCanvasElement, HtmlElement, ImageData};

use crate::camera::Camera;
use crate::map::{Frame, Map};
use crate::session::Session;

/// The page's canvas (`#map`) and HUD (`#hud`).
pub(super) struct Canvas {
    canvas: HtmlCanvasElement,
    ctx: CanvasRenderingContext2d,
    hud: Option<HtmlElement>,
}

impl Canvas {
    /// The page's canvas and HUD, if it has a canvas with a 2D context.
    pub(super) fn find(document: &Document) -> Option<Canvas> {
        let canvas: HtmlCanvasElement = document.get_element_by_id("map")?.dyn_into().ok()?;
        let ctx = canvas.get_context("2d").ok()??.dyn_into().ok()?;
        let hud = document.get_element_by_id("hud").and_then(|e| e.dyn_into().ok());
        Some(Canvas { canvas, ctx, hud })
    }

    pub(super) fn element(&self) -> &HtmlCanvasElement {
        &self.canvas
    }

    /// Show `text` in the HUD.
    pub(super) fn hud(&self, text: &str) {
        if let Some(h) = &self.hud
            && h.text_content().as_deref() != Some(text)
        {
            h.set_text_content(Some(text));
        }
    }

    /// Draw the map around `camera`, `span` metres from the centre to the nearer edge.
    pub(super) fn draw(&self, map: &mut Map, session: &Session, camera: &Camera, span: f32) {
        let (w, h) = (self.canvas.client_width().max(1) as u32, self.canvas.client_height().max(1) as u32);
        if self.canvas.width() != w || self.canvas.height() != h {
            self.canvas.set_width(w);
            self.canvas.set_height(h);
        }
        let frame = Frame::new(w as usize, h as usize, camera, span.max(1.0));
        map.paint(session, &frame);
        if let Ok(img) = ImageData::new_with_u8_clamped_array_and_sh(Clamped(&map.pixels[..]), w, h) {
            let _ = self.ctx.put_image_data(&img, 0.0, 0.0);
        }
        self.overlay(session, &frame);
    }

    fn polygon(&self, points: &[[f32; 2]]) {
        let ctx = &self.ctx;
        ctx.begin_path();
        for (i, p) in points.iter().enumerate() {
            if i == 0 {
                ctx.move_to(p[0].into(), p[1].into());
            } else {
                ctx.line_to(p[0].into(), p[1].into());
            }
        }
        ctx.close_path();
    }

    fn overlay(&self, session: &Session, f: &Frame) {
        let ctx = &self.ctx;
        let state = session.state();
        let Some(w) = state.welcome() else { return };
        let grid = &w.world.grid;
        // Cells granted and not expanded yet.
        ctx.set_stroke_style_str("rgba(255, 210, 80, 0.55)");
        ctx.set_line_width(1.0);
        for (c, held) in state.cells() {
            if !held.expanding {
                continue;
            }
            let [x, z] = grid.cell_origin(*c);
            let s = grid.cell_size;
            let corners = [[x, z], [x + s, z], [x + s, z + s], [x, z + s]].map(|p| f.to_screen(p));
            self.polygon(&corners);
            ctx.stroke();
        }
        // The area of interest of the viewpoint last sent, and its hysteresis band.
        if let Some(vp) = state.viewpoint() {
            let c = f.to_screen(vp.position);
            let r = vp.radius.min(w.aoi.max_radius);
            for (radius, style, dash) in
                [(r, "rgba(120, 200, 255, 0.9)", false), (r + w.aoi.hysteresis, "rgba(120, 200, 255, 0.5)", true)]
            {
                ctx.set_stroke_style_str(style);
                ctx.set_line_width(1.5);
                let segments = js_sys::Array::new();
                if dash {
                    segments.push(&JsValue::from(6.0));
                    segments.push(&JsValue::from(6.0));
                }
                let _ = ctx.set_line_dash(&segments);
                ctx.begin_path();
                let _ =
                    ctx.arc(c[0].into(), c[1].into(), (radius / f.metres_per_px).into(), 0.0, std::f64::consts::TAU);
                ctx.stroke();
            }
            let _ = ctx.set_line_dash(&js_sys::Array::new());
        }
        // The camera: its view (60°) and an arrow, heading up.
        let (cx, cy) = (f.width as f32 * 0.5, f.height as f32 * 0.5);
        let reach = 90.0f32;
        let half = 30f32.to_radians();
        ctx.set_fill_style_str("rgba(255, 255, 255, 0.12)");
        self.polygon(&[
            [cx, cy],
            [cx - reach * half.sin(), cy - reach * half.cos()],
            [cx + reach * half.sin(), cy - reach * half.cos()],
        ]);
        ctx.fill();
        ctx.set_fill_style_str("#ffffff");
        ctx.set_stroke_style_str("#000000");
        self.polygon(&[[cx, cy - 11.0], [cx + 7.0, cy + 7.0], [cx, cy + 3.0], [cx - 7.0, cy + 7.0]]);
        ctx.fill();
        ctx.stroke();
        // North (+z) and a scale bar, bottom right.
        let n = f.to_screen([f.centre[0], f.centre[1] + 1.0]);
        let d = [n[0] - cx, n[1] - cy];
        let len = (d[0] * d[0] + d[1] * d[1]).sqrt().max(1e-6);
        let (ax, ay) = (f.width as f32 - 40.0, f.height as f32 - 70.0);
        ctx.set_stroke_style_str("#ffffff");
        ctx.set_line_width(2.0);
        ctx.begin_path();
        ctx.move_to(ax.into(), ay.into());
        ctx.line_to((ax + d[0] / len * 22.0).into(), (ay + d[1] / len * 22.0).into());
        ctx.stroke();
        ctx.set_fill_style_str("#ffffff");
        ctx.set_font("12px monospace");
        let _ = ctx.fill_text("+z", (ax + d[0] / len * 30.0 - 8.0).into(), (ay + d[1] / len * 30.0 + 4.0).into());
        let metres = nice(120.0 * f.metres_per_px);
        let px = metres / f.metres_per_px;
        let (bx, by) = (f.width as f32 - 20.0 - px, f.height as f32 - 20.0);
        ctx.begin_path();
        ctx.move_to(bx.into(), by.into());
        ctx.line_to((bx + px).into(), by.into());
        ctx.stroke();
        let _ = ctx.fill_text(&format!("{metres} m"), bx.into(), (by - 6.0).into());
    }
}

/// The largest of 1, 2, 5 × a power of ten at most `m`.
fn nice(m: f32) -> f32 {
    let p = 10f32.powf(m.max(1e-3).log10().floor());
    [5.0, 2.0, 1.0].into_iter().map(|k| k * p).find(|v| *v <= m).unwrap_or(p)
}
