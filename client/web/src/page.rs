//! What the page reads and what it tells: the server's `/connect.json` ([`ConnectInfo`]), the state a test reads
//! through `window.canopyState()` ([`PageState`]) and the digest of the instances held ([`held_digest`]), which a
//! native test recomputes from the world function.

use canopy_client::state::{ClientState, instance_seed};
use canopy_protocol::{CellCoord, InstanceId};
use canopy_worlds::world::{CellKey, World};
use serde::{Deserialize, Serialize};

use crate::session::Options;

/// The document the server serves at `/connect.json`: where its WebTransport endpoint is on the page's own host,
/// and the SHA-256 of its certificate, for `serverCertificateHashes`.
#[derive(Clone, Debug, PartialEq, Deserialize)]
pub struct ConnectInfo {
    /// The UDP port.
    pub port: u16,
    /// The endpoint's path (`/canopy`).
    pub path: String,
    /// The certificate's SHA-256, 64 lowercase hexadecimal digits.
    pub certificate_hash: String,
}

impl ConnectInfo {
    /// Parse and check the document.
    pub fn parse(text: &str) -> Result<ConnectInfo, String> {
        let info: ConnectInfo = serde_json::from_str(text).map_err(|e| format!("connect.json: {e}"))?;
        if info.port == 0 {
            return Err("connect.json: port 0".into());
        }
        if !info.path.starts_with('/') || info.path.chars().any(|c| c.is_whitespace() || c == '#') {
            return Err(format!("connect.json: bad path {:?}", info.path));
        }
        info.hash()?;
        Ok(info)
    }

    /// The certificate hash's 32 bytes.
    pub fn hash(&self) -> Result<[u8; 32], String> {
        let h = self.certificate_hash.as_bytes();
        let digit = |c: u8| match c {
            b'0'..=b'9' => Some(c - b'0'),
            b'a'..=b'f' => Some(c - b'a' + 10),
            _ => None,
        };
        if h.len() != 64 {
            return Err(format!("connect.json: certificate_hash has {} characters, not 64", h.len()));
        }
        let mut out = [0u8; 32];
        for (i, pair) in h.chunks(2).enumerate() {
            match (digit(pair[0]), digit(pair[1])) {
                (Some(a), Some(b)) => out[i] = a << 4 | b,
                _ => return Err("connect.json: certificate_hash is not lowercase hexadecimal".into()),
            }
        }
        Ok(out)
    }

    /// The WebTransport URL on `host` (the page's host name; an IPv6 address is bracketed).
    pub fn url(&self, host: &str) -> String {
        let host = if host.contains(':') && !host.starts_with('[') { format!("[{host}]") } else { host.to_owned() };
        format!("https://{host}:{}{}", self.port, self.path)
    }
}

/// The session's options from the page's query string (`?x=..&z=..&yaw=..&radius=..`, each optional; `yaw` in
/// degrees): the start on (x, z) where both are given, else the default start.
pub fn query_options(search: &str) -> Options {
    let mut opts = Options::default();
    let (mut x, mut z) = (None, None);
    for pair in search.trim_start_matches('?').split('&') {
        let Some((k, v)) = pair.split_once('=') else { continue };
        if k == "token" {
            opts.token = unhex(v);
            continue;
        }
        let Ok(v) = v.parse::<f32>() else { continue };
        if !v.is_finite() {
            continue;
        }
        match k {
            "x" => x = Some(v),
            "z" => z = Some(v),
            "yaw" => opts.yaw = v.to_radians(),
            "radius" if v > 0.0 => opts.radius = v,
            _ => {}
        }
    }
    if let (Some(x), Some(z)) = (x, z) {
        opts.start = Some([x, z]);
    }
    opts
}

/// Hexadecimal digits as bytes (`None`: empty, odd or not hexadecimal).
fn unhex(s: &str) -> Option<Vec<u8>> {
    if s.is_empty() || !s.len().is_multiple_of(2) {
        return None;
    }
    (0..s.len()).step_by(2).map(|i| u8::from_str_radix(s.get(i..i + 2)?, 16).ok()).collect()
}

/// FNV-1a, 64 bits.
struct Fnv(u64);

impl Fnv {
    fn eat(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 ^= u64::from(b);
            self.0 = self.0.wrapping_mul(0x0100_0000_01b3);
        }
    }
}

/// The digest of the instances a client holds, and how many there are.
///
/// FNV-1a 64 (offset basis `0xcbf29ce484222325`, prime `0x100000001b3`) over, all integers little-endian: the
/// instance count as u64; then for every instance held ([`ClientState::instances`]: felled records skipped, records
/// of cells still arriving included), in the order of (cell x, cell z, index in the cell): cell x as i32, cell z
/// as i32, the index as u16, the species id as u8, the position steps in the cell `qx`, `qz` as u16 each (the
/// record's, which are `World::steps` of the placement), the instance seed as u64
/// (`instance_seed(world seed, id)`), the number of parameter overrides as u16, then each override's slot as u16
/// and value's f32 bits as u32, by slot.
pub fn held_digest(state: &ClientState) -> (u64, usize) {
    // Cells imply a welcome; without one there is nothing to hash but the zero count.
    let seed = state.welcome().map_or(0, |w| w.world.seed);
    let mut cells: Vec<_> = state.cells().iter().collect();
    cells.sort_by_key(|(c, _)| (c.x, c.z));
    let count: usize = cells.iter().map(|(_, h)| h.records.len() - h.felled.len()).sum();
    let mut f = Fnv(0xcbf2_9ce4_8422_2325);
    f.eat(&(count as u64).to_le_bytes());
    for (c, h) in cells {
        for (i, r) in h.records.iter().enumerate() {
            let index = i as u16;
            if h.felled.contains(&index) {
                continue;
            }
            f.eat(&c.x.to_le_bytes());
            f.eat(&c.z.to_le_bytes());
            f.eat(&index.to_le_bytes());
            f.eat(&[r.species]);
            f.eat(&r.qx().to_le_bytes());
            f.eat(&r.qz().to_le_bytes());
            let id = canopy_protocol::InstanceId::new(*c, index).expect("a held cell can be named");
            f.eat(&instance_seed(seed, id).to_le_bytes());
            let lo = h.overrides.partition_point(|o| o.record < index);
            let hi = h.overrides.partition_point(|o| o.record <= index);
            f.eat(&((hi - lo) as u16).to_le_bytes());
            for o in &h.overrides[lo..hi] {
                f.eat(&o.slot.to_le_bytes());
                f.eat(&o.value.to_bits().to_le_bytes());
            }
        }
    }
    (f.0, count)
}

/// [`held_digest`] computed from the world function itself rather than from a client: the digest of every instance
/// of `cells` as [`World::expand_cell`] places them. A second, independent writing of the same definition, for
/// tests that check a client (a browser's page included) against the world.
pub fn world_digest(world: &World, cells: &[CellCoord]) -> (u64, usize) {
    let mut cells = cells.to_vec();
    cells.sort_by_key(|c| (c.x, c.z));
    let mut items = Vec::new();
    for c in cells {
        let key = CellKey { x: c.x, z: c.z };
        for (i, p) in world.expand_cell(key).iter().enumerate() {
            let id = InstanceId::new(c, i as u16).unwrap();
            items.push((c, i as u16, p.species as u8, world.steps(key, p), world.seed, id, p.params.clone()));
        }
    }
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut eat = |bytes: &[u8]| {
        for &b in bytes {
            h = (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01b3);
        }
    };
    eat(&(items.len() as u64).to_le_bytes());
    for (c, i, species, [qx, qz], seed, id, params) in &items {
        eat(&c.x.to_le_bytes());
        eat(&c.z.to_le_bytes());
        eat(&i.to_le_bytes());
        eat(&[*species]);
        eat(&qx.to_le_bytes());
        eat(&qz.to_le_bytes());
        eat(&canopy_worlds::world::instance_seed(*seed, *id).to_le_bytes());
        eat(&(params.len() as u16).to_le_bytes());
        for (slot, v) in params {
            eat(&slot.to_le_bytes());
            eat(&v.to_bits().to_le_bytes());
        }
    }
    (h, items.len())
}

/// The viewpoint last sent, as the page state shows it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SentViewpoint {
    /// Its sequence number.
    pub seq: u32,
    /// (x, z).
    pub position: [f32; 2],
    /// The radius asked for.
    pub radius: f32,
}

/// What `window.canopyState()` returns (as JSON).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct PageState {
    /// `"connecting"`, `"streaming"` or `"closed"`.
    pub phase: &'static str,
    /// Why the session ended or could not start (`null` while it runs).
    pub error: Option<String>,
    /// Whether the area of interest is complete ([`ClientState::is_complete`]).
    pub complete: bool,
    /// Instances held.
    pub records: usize,
    /// Cells held (complete or not).
    pub cells: usize,
    /// Granted cells waiting for their expansion.
    pub pending: usize,
    /// Cells still to come ([`ClientState::missing`]).
    pub missing: usize,
    /// Cells this page expanded.
    pub expanded: u64,
    /// Far-view summary nodes held ([`ClientState::summaries`]).
    pub far_nodes: usize,
    /// The camera, x, y, z.
    pub position: [f32; 3],
    /// The camera's heading, radians (0 looks along +z, π/2 along +x).
    pub yaw: f32,
    /// [`held_digest`] as 16 lowercase hexadecimal digits.
    pub digest: String,
    /// The cells held, `[x, z]`, sorted.
    pub held_cells: Vec<[i32; 2]>,
    /// The viewpoint last sent (`null` before the welcome).
    pub viewpoint: Option<SentViewpoint>,
    /// The world's name (`null` before the welcome).
    pub world: Option<String>,
    /// Species held and in the table.
    pub species: [usize; 2],
    /// Frame bytes read and written.
    pub bytes: [u64; 2],
    /// The last animation frame's time, milliseconds (smoothed).
    pub frame_ms: f64,
    /// The longest animation frame of the last second or so, milliseconds.
    pub frame_ms_max: f64,
    /// Whether a scripted walk is under way.
    pub walking: bool,
    /// The 3D view: `"webgpu: <adapter>"`, `"none: <reason>"`, or `"starting"` while the GPU is set up.
    pub renderer: String,
    /// Frames the 3D view has drawn.
    pub frames: u64,
    /// The renderer's jobs waiting (amplification, voxelisation, canopy tiles): 0 once what is in view is built.
    pub jobs: usize,
    /// Whether the last frame drew everything in view at its wanted level (nothing queued, running or waiting for
    /// its upload).
    pub settled: bool,
    /// Whether the page said hello with an editor's token (`?token=HEX`).
    pub editor: bool,
    /// The edits asked for lately, oldest first.
    pub edits: Vec<EditState>,
}

/// An edit as the page state shows it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct EditState {
    /// Its request number.
    pub request: u32,
    /// `"waiting"`, `"ok"` or why it was refused.
    pub outcome: String,
    /// The instance made or changed, `[cell x, cell z, index]`, once applied.
    pub instance: Option<[i32; 3]>,
}

impl PageState {
    /// The state of `session` with the camera at `position` heading `yaw`.
    pub fn of(session: &crate::session::Session, position: [f32; 3], yaw: f32) -> PageState {
        let mut s = PageState::summary(session, position, yaw);
        let (digest, _) = held_digest(session.state());
        s.digest = format!("{digest:016x}");
        s.held_cells = session.state().cells().keys().map(|c| [c.x, c.z]).collect();
        s.held_cells.sort_unstable();
        s
    }

    /// [`PageState::of`] without the digest and the list of cells (empty), which cost a pass over every instance
    /// held: what the HUD shows every frame.
    pub fn summary(session: &crate::session::Session, position: [f32; 3], yaw: f32) -> PageState {
        let state = session.state();
        let (digest, held_cells) = (String::new(), Vec::new());
        let records = state.record_count();
        PageState {
            phase: session.link().name(),
            error: session.error().map(str::to_owned),
            complete: state.is_complete(),
            records,
            cells: state.cells().len(),
            pending: session.pending(),
            missing: state.missing(),
            expanded: session.expanded(),
            far_nodes: state.summaries().len(),
            position,
            yaw,
            digest,
            held_cells,
            viewpoint: state.viewpoint().map(|v| SentViewpoint { seq: v.seq, position: v.position, radius: v.radius }),
            world: session.welcome().map(|w| w.world.name.clone()),
            species: [state.species_held(), session.welcome().map_or(0, |w| w.species.len())],
            bytes: [session.bytes_in(), session.bytes_out()],
            frame_ms: 0.0,
            frame_ms_max: 0.0,
            walking: false,
            renderer: "starting".into(),
            frames: 0,
            jobs: 0,
            settled: false,
            editor: session.editor(),
            edits: session
                .edits()
                .map(|e| EditState {
                    request: e.request,
                    outcome: match &e.outcome {
                        None => "waiting".into(),
                        Some(Ok(_)) => "ok".into(),
                        Some(Err(why)) => why.clone(),
                    },
                    instance: match &e.outcome {
                        Some(Ok(id)) => Some([id.cell().x, id.cell().z, i32::from(id.index())]),
                        _ => None,
                    },
                })
                .collect(),
        }
    }

    /// As JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("the page state serialises")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HASH: &str = "00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff";

    #[test]
    fn connect_json_is_parsed_checked_and_gives_the_url_on_the_pages_host() {
        let text = format!(r#"{{"port": 4433, "path": "/canopy", "certificate_hash": "{HASH}"}}"#);
        let info = ConnectInfo::parse(&text).unwrap();
        assert_eq!(info.url("127.0.0.1"), "https://127.0.0.1:4433/canopy");
        assert_eq!(info.url("::1"), "https://[::1]:4433/canopy");
        let h = info.hash().unwrap();
        assert_eq!((h[0], h[1], h[15], h[31]), (0x00, 0x11, 0xff, 0xff));
        for bad in [
            format!(r#"{{"port": 0, "path": "/canopy", "certificate_hash": "{HASH}"}}"#),
            format!(r#"{{"port": 1, "path": "canopy", "certificate_hash": "{HASH}"}}"#),
            format!(r#"{{"port": 1, "path": "/canopy", "certificate_hash": "{}"}}"#, HASH.to_uppercase()),
            format!(r#"{{"port": 1, "path": "/canopy", "certificate_hash": "{}"}}"#, &HASH[2..]),
            r#"{"port": 1, "path": "/canopy"}"#.to_owned(),
            "not json".to_owned(),
        ] {
            assert!(ConnectInfo::parse(&bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_query_sets_the_start_heading_and_radius() {
        let o = query_options("?x=100&z=-20.5&yaw=90&radius=300&other=1");
        assert_eq!((o.start, o.radius), (Some([100.0, -20.5]), 300.0));
        assert!((o.yaw - std::f32::consts::FRAC_PI_2).abs() < 1e-6);
        let o = query_options("?x=1&radius=-3&yaw=NaN");
        assert_eq!(o, Options::default());
        assert_eq!(query_options(""), Options::default());
        assert_eq!(query_options("?token=00ff7a").token, Some(vec![0x00, 0xff, 0x7a]));
        for bad in ["?token=", "?token=abc", "?token=zz"] {
            assert_eq!(query_options(bad).token, None, "{bad}");
        }
    }

    #[test]
    fn the_digest_of_nothing_is_fnv_of_a_zero_count() {
        // FNV-1a written out again, over the eight bytes of a zero count.
        let mut h: u64 = 0xcbf2_9ce4_8422_2325;
        for _ in 0..8 {
            h = h.wrapping_mul(0x0100_0000_01b3);
        }
        assert_eq!(held_digest(&ClientState::new()), (h, 0));
    }
}
