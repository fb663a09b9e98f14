//! Event handling: keys held and pressed, the mouse, and winit's
//! application events.

use super::*;
use crate::app::camera::Input;
use planet_client::quality::QualityMode;
use std::time::Instant;
use winit::application::ApplicationHandler;
use winit::event::{ElementState, KeyEvent, MouseButton, MouseScrollDelta, WindowEvent};
use winit::event_loop::ActiveEventLoop;
use winit::keyboard::{KeyCode, PhysicalKey};
use winit::window::WindowId;

impl App {
    pub(super) fn key(&mut self, event_loop: &ActiveEventLoop, ev: &KeyEvent) {
        let PhysicalKey::Code(code) = ev.physical_key else {
            return;
        };
        let datum = self.header.datum;
        match ev.state {
            ElementState::Pressed => {
                self.keys.insert(code);
                if ev.repeat {
                    return;
                }
                match code {
                    KeyCode::Escape => event_loop.exit(),
                    KeyCode::Tab => self.ctl.toggle(&datum),
                    KeyCode::KeyC => self.crack_fixing = !self.crack_fixing,
                    KeyCode::KeyH => self.show_hud = !self.show_hud,
                    KeyCode::KeyG => {
                        self.view = (self.view + 1) % self.views.len();
                        self.ctl = self.views[self.view].1;
                    }
                    _ => {}
                }
            }
            ElementState::Released => {
                self.keys.remove(&code);
            }
        }
    }

    pub(super) fn held(&self) -> Input {
        let k = |c: &[KeyCode]| c.iter().any(|c| self.keys.contains(c));
        let axis =
            |pos: &[KeyCode], neg: &[KeyCode]| f64::from(k(pos) as u8) - f64::from(k(neg) as u8);
        Input {
            forward: axis(
                &[KeyCode::KeyW, KeyCode::ArrowUp],
                &[KeyCode::KeyS, KeyCode::ArrowDown],
            ),
            right: axis(
                &[KeyCode::KeyD, KeyCode::ArrowRight],
                &[KeyCode::KeyA, KeyCode::ArrowLeft],
            ),
            up: axis(
                &[KeyCode::KeyE, KeyCode::PageUp],
                &[KeyCode::KeyQ, KeyCode::PageDown],
            ),
            boost: k(&[KeyCode::ShiftLeft, KeyCode::ShiftRight]),
            ..self.input
        }
    }
}

impl ApplicationHandler for App {
    fn resumed(&mut self, event_loop: &ActiveEventLoop) {
        if self.gfx.is_some() {
            return;
        }
        match Gfx::new(event_loop, self.opts.width, self.opts.height) {
            Ok(g) => {
                eprintln!("planet-view: adapter {}", g.adapter_name);
                if g.cpu_adapter && self.opts.target_fps.is_none() {
                    let fps = default_target_fps(true);
                    if let Some(c) = self.client.as_mut() {
                        c.client.quality_mut().set_mode(QualityMode::TargetFps(fps));
                    }
                    eprintln!(
                        "planet-view: rendering on the CPU; aiming at {fps} fps (set --target-fps to change)"
                    );
                }
                if let Some(mhz) = g
                    .window
                    .current_monitor()
                    .and_then(|m| m.refresh_rate_millihertz())
                    .filter(|&mhz| mhz > 0)
                {
                    self.refresh_s = 1e3 / f64::from(mhz);
                }
                self.gfx = Some(g);
                self.last_frame = Instant::now();
            }
            Err(e) => self.fail(event_loop, e),
        }
    }

    fn window_event(&mut self, event_loop: &ActiveEventLoop, _id: WindowId, event: WindowEvent) {
        match event {
            WindowEvent::CloseRequested => event_loop.exit(),
            WindowEvent::Resized(size) => {
                if let Some(g) = self.gfx.as_mut() {
                    g.resize(size.width, size.height);
                }
            }
            WindowEvent::KeyboardInput { event, .. } => self.key(event_loop, &event),
            WindowEvent::ModifiersChanged(_) => {}
            WindowEvent::MouseInput { state, button, .. } => {
                if matches!(button, MouseButton::Left | MouseButton::Right) {
                    self.dragging = state == ElementState::Pressed;
                }
            }
            WindowEvent::CursorMoved { position, .. } => {
                let p = (position.x, position.y);
                if let (true, Some(last)) = (self.dragging, self.last_cursor) {
                    self.input.drag.0 += p.0 - last.0;
                    self.input.drag.1 += p.1 - last.1;
                }
                self.last_cursor = Some(p);
            }
            WindowEvent::MouseWheel { delta, .. } => {
                self.input.scroll += match delta {
                    MouseScrollDelta::LineDelta(_, y) => y as f64,
                    MouseScrollDelta::PixelDelta(p) => p.y / 40.0,
                };
            }
            WindowEvent::RedrawRequested => {
                if let Err(e) = self.redraw(event_loop) {
                    self.fail(event_loop, e);
                }
            }
            _ => {}
        }
    }

    fn about_to_wait(&mut self, _event_loop: &ActiveEventLoop) {
        if let Some(g) = &self.gfx {
            g.window.request_redraw();
        }
    }
}
