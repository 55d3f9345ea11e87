//! How the client trusts a server: by the SHA-256 fingerprint of its self-signed certificate (pinned), or, for
//! local use only, not at all (`--insecure`). Either way the TLS 1.3 handshake signatures are verified, so the
//! server proves it holds the certificate's key.

use std::sync::Arc;

use canopy_protocol::messages::certificate_fingerprint;
use quinn::rustls;
use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::crypto::{CryptoProvider, verify_tls12_signature, verify_tls13_signature};
use rustls::pki_types::{CertificateDer, ServerName, UnixTime};
use rustls::{DigitallySignedStruct, SignatureScheme};

/// Which server certificates the client accepts.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Trust {
    /// Only the certificate with this SHA-256 fingerprint (64 hex digits, as `canopy-server` prints it).
    Pinned(String),
    /// Any certificate: for local use only.
    Insecure,
}

impl Trust {
    /// Parse a fingerprint as printed by the server (hex, colons and case ignored).
    pub fn pinned(fingerprint: &str) -> Option<Trust> {
        let hex: String = fingerprint.chars().filter(|c| *c != ':').collect::<String>().to_ascii_lowercase();
        (hex.len() == 64 && hex.chars().all(|c| c.is_ascii_hexdigit())).then_some(Trust::Pinned(hex))
    }

    /// The trust the command-line flags ask for: `--cert-fingerprint` (pinned) or `--insecure`; one is required.
    pub fn from_flags(fingerprint: Option<&str>, insecure: bool) -> Result<Trust, TrustFlagsError> {
        match (fingerprint, insecure) {
            (Some(f), _) => Trust::pinned(f).ok_or_else(|| TrustFlagsError::NotAFingerprint(f.to_owned())),
            (None, true) => Ok(Trust::Insecure),
            (None, false) => Err(TrustFlagsError::Missing),
        }
    }
}

/// Why the trust flags name no trust.
#[derive(Debug, thiserror::Error)]
pub enum TrustFlagsError {
    /// `--cert-fingerprint` is not 64 hex digits.
    #[error("`{0}` is not a SHA-256 fingerprint (64 hex digits)")]
    NotAFingerprint(String),
    /// Neither flag was given.
    #[error("pass --cert-fingerprint (printed by canopy-server) or --insecure for local use")]
    Missing,
}

#[derive(Debug)]
struct Verifier {
    trust: Trust,
    provider: Arc<CryptoProvider>,
}

impl ServerCertVerifier for Verifier {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        _intermediates: &[CertificateDer<'_>],
        _server_name: &ServerName<'_>,
        _ocsp_response: &[u8],
        _now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        match &self.trust {
            Trust::Insecure => Ok(ServerCertVerified::assertion()),
            Trust::Pinned(want) if certificate_fingerprint(end_entity.as_ref()) == *want => {
                Ok(ServerCertVerified::assertion())
            }
            Trust::Pinned(_) => {
                Err(rustls::Error::InvalidCertificate(rustls::CertificateError::ApplicationVerificationFailure))
            }
        }
    }

    fn verify_tls12_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        verify_tls12_signature(message, cert, dss, &self.provider.signature_verification_algorithms)
    }

    fn verify_tls13_signature(
        &self,
        message: &[u8],
        cert: &CertificateDer<'_>,
        dss: &DigitallySignedStruct,
    ) -> Result<HandshakeSignatureValid, rustls::Error> {
        verify_tls13_signature(message, cert, dss, &self.provider.signature_verification_algorithms)
    }

    fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
        self.provider.signature_verification_algorithms.supported_schemes()
    }
}

/// Why the client's TLS or QUIC configuration could not be built.
#[derive(Debug, thiserror::Error)]
pub enum TlsError {
    /// rustls rejected the configuration.
    #[error("TLS configuration: {0}")]
    Rustls(#[from] rustls::Error),
    /// quinn rejected the TLS configuration.
    #[error("QUIC TLS configuration: {0}")]
    Quic(String),
}

/// How long a connection may hear nothing before it counts as lost, by default.
pub const IDLE_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(30);

/// A quinn client configuration trusting servers as `trust` says, speaking ALPN `canopy/1`.
pub fn client_config(trust: Trust) -> Result<quinn::ClientConfig, TlsError> {
    client_config_idle(trust, IDLE_TIMEOUT)
}

/// [`client_config`] with a connection counted as lost after `idle` of silence (keep-alives at a quarter of it).
pub fn client_config_idle(trust: Trust, idle: std::time::Duration) -> Result<quinn::ClientConfig, TlsError> {
    client_config_alpn(trust, idle, canopy_protocol::ALPN)
}

/// [`client_config_idle`] speaking `alpn`: `canopy/1`, or `h3` for a WebTransport session as a browser opens it.
pub fn client_config_alpn(
    trust: Trust,
    idle: std::time::Duration,
    alpn: &[u8],
) -> Result<quinn::ClientConfig, TlsError> {
    let provider = Arc::new(rustls::crypto::ring::default_provider());
    let verifier = Arc::new(Verifier { trust, provider: Arc::clone(&provider) });
    let mut tls = rustls::ClientConfig::builder_with_provider(provider)
        .with_protocol_versions(&[&rustls::version::TLS13])?
        .dangerous()
        .with_custom_certificate_verifier(verifier)
        .with_no_client_auth();
    tls.alpn_protocols = vec![alpn.to_vec()];
    let crypto = quinn::crypto::rustls::QuicClientConfig::try_from(tls).map_err(|e| TlsError::Quic(e.to_string()))?;
    let mut cfg = quinn::ClientConfig::new(Arc::new(crypto));
    let mut t = quinn::TransportConfig::default();
    t.max_concurrent_uni_streams(quinn::VarInt::from_u32(16))
        .max_concurrent_bidi_streams(quinn::VarInt::from_u32(0))
        .stream_receive_window(quinn::VarInt::from_u32(1 << 20))
        .receive_window(quinn::VarInt::from_u32(4 << 20))
        .keep_alive_interval(Some(idle / 4))
        .max_idle_timeout(idle.try_into().ok());
    cfg.transport_config(Arc::new(t));
    Ok(cfg)
}
