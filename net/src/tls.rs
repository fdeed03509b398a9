//! Per-run certificates and fingerprint pinning.
//!
//! Every coordinator and worker generates a new self-signed certificate when it starts.
//! Clients do not check names or chains: they accept the server only if the SHA-256 of its
//! certificate equals the fingerprint they were given out of band (the coordinator's on the
//! command line or in a file; the peers' from the coordinator over the already pinned
//! connection). That is exactly as strong as the channel that delivered the fingerprint.
//!
//! Between workers the pinning is mutual: a worker's server side demands a client
//! certificate ([`server_config`] with `client_auth`), the dialling peer presents its own
//! ([`client_config`] with `id`), and the acceptor compares [`peer_fingerprint`] with the
//! fingerprint the coordinator handed out for the rank the peer claims.

use anyhow::{Context, Result};
use quinn::crypto::rustls::{QuicClientConfig, QuicServerConfig};
use rustls::client::danger::{HandshakeSignatureValid, ServerCertVerified, ServerCertVerifier};
use rustls::crypto::CryptoProvider;
use rustls::pki_types::{CertificateDer, PrivateKeyDer, PrivatePkcs8KeyDer, ServerName, UnixTime};
use rustls::server::danger::{ClientCertVerified, ClientCertVerifier};
use rustls::{DigitallySignedStruct, SignatureScheme};
use std::sync::Arc;
use strata_common::wire::Fingerprint;

/// ALPN of the protocol, so a QUIC endpoint of anything else fails the handshake.
pub const ALPN: &[u8] = b"strata/1";
/// The server name clients ask for (never checked; the fingerprint is).
pub const SERVER_NAME: &str = "strata";

/// A certificate and its key, generated for this process.
pub struct Identity {
    /// The DER certificate.
    pub cert: CertificateDer<'static>,
    key: PrivatePkcs8KeyDer<'static>,
    /// SHA-256 of `cert`.
    pub fingerprint: Fingerprint,
}

impl Identity {
    /// A fresh self-signed certificate (ECDSA P-256).
    pub fn generate() -> Result<Identity> {
        let ck = rcgen::generate_simple_self_signed(vec![SERVER_NAME.to_string()])
            .context("generating the run certificate")?;
        let cert = ck.cert.der().clone();
        let key = PrivatePkcs8KeyDer::from(ck.signing_key.serialize_der());
        Ok(Identity {
            fingerprint: fingerprint_of(&cert),
            cert,
            key,
        })
    }
}

fn provider() -> Arc<CryptoProvider> {
    Arc::new(rustls::crypto::ring::default_provider())
}

/// SHA-256 of a DER certificate.
pub fn fingerprint_of(der: &[u8]) -> Fingerprint {
    let d = ring::digest::digest(&ring::digest::SHA256, der);
    d.as_ref().try_into().expect("SHA-256 is 32 bytes")
}

/// Lower-case hex.
pub fn to_hex(fp: &Fingerprint) -> String {
    fp.iter().map(|b| format!("{b:02x}")).collect()
}

/// The first 8 characters of `s` and how many there are, for messages about a value that
/// may be a secret given in the wrong place (a run's secret is 64 hex digits too, as a
/// fingerprint is): enough to tell which value it was, not enough to use it.
pub fn abbreviated(s: &str) -> String {
    let n = s.chars().count();
    match n {
        0..=8 => format!("{s:?}"),
        _ => format!(
            "{:?}… ({n} characters)",
            s.chars().take(8).collect::<String>()
        ),
    }
}

/// Parses 64 hex digits (colons and whitespace allowed, as `openssl x509 -fingerprint` prints).
pub fn parse_fingerprint(s: &str) -> Result<Fingerprint> {
    let digits: String = s
        .chars()
        .filter(|c| !c.is_whitespace() && *c != ':')
        .collect();
    anyhow::ensure!(
        digits.len() == 64 && digits.chars().all(|c| c.is_ascii_hexdigit()),
        "expected a SHA-256 fingerprint of 64 hex digits, got {}",
        abbreviated(s.trim())
    );
    let mut fp = [0u8; 32];
    for (i, b) in fp.iter_mut().enumerate() {
        *b = u8::from_str_radix(&digits[2 * i..2 * i + 2], 16).unwrap();
    }
    Ok(fp)
}

/// Server side of an endpoint with this identity. With `client_auth`, every client must
/// present a certificate and prove it holds its key; which certificate is acceptable is
/// the application's check ([`peer_fingerprint`] against the fingerprint it expects).
pub fn server_config(
    id: &Identity,
    transport: Arc<quinn::TransportConfig>,
    client_auth: bool,
) -> Result<quinn::ServerConfig> {
    let builder = rustls::ServerConfig::builder_with_provider(provider())
        .with_protocol_versions(&[&rustls::version::TLS13])?;
    let builder = if client_auth {
        builder.with_client_cert_verifier(Arc::new(AnyClientCert {
            provider: provider(),
        }))
    } else {
        builder.with_no_client_auth()
    };
    let mut crypto = builder.with_single_cert(
        vec![id.cert.clone()],
        PrivateKeyDer::Pkcs8(id.key.clone_key()),
    )?;
    crypto.alpn_protocols = vec![ALPN.to_vec()];
    let mut cfg = quinn::ServerConfig::with_crypto(Arc::new(QuicServerConfig::try_from(crypto)?));
    cfg.transport_config(transport);
    Ok(cfg)
}

/// Client side that accepts only the server whose certificate hashes to `pinned`, and
/// presents `id`'s certificate when the server asks for one.
pub fn client_config(
    pinned: Fingerprint,
    transport: Arc<quinn::TransportConfig>,
    id: Option<&Identity>,
) -> Result<quinn::ClientConfig> {
    let provider = provider();
    let builder = rustls::ClientConfig::builder_with_provider(provider.clone())
        .with_protocol_versions(&[&rustls::version::TLS13])?
        .dangerous()
        .with_custom_certificate_verifier(Arc::new(PinnedVerifier { pinned, provider }));
    let mut crypto = match id {
        Some(id) => builder.with_client_auth_cert(
            vec![id.cert.clone()],
            PrivateKeyDer::Pkcs8(id.key.clone_key()),
        )?,
        None => builder.with_no_client_auth(),
    };
    crypto.alpn_protocols = vec![ALPN.to_vec()];
    let mut cfg = quinn::ClientConfig::new(Arc::new(QuicClientConfig::try_from(crypto)?));
    cfg.transport_config(transport);
    Ok(cfg)
}

/// The handshake-signature checks both verifiers share: the peer must hold the key of the
/// certificate it presents (the provider's algorithms, TLS 1.2 and 1.3).
macro_rules! handshake_signatures {
    () => {
        fn verify_tls12_signature(
            &self,
            message: &[u8],
            cert: &CertificateDer<'_>,
            dss: &DigitallySignedStruct,
        ) -> Result<HandshakeSignatureValid, rustls::Error> {
            rustls::crypto::verify_tls12_signature(
                message,
                cert,
                dss,
                &self.provider.signature_verification_algorithms,
            )
        }

        fn verify_tls13_signature(
            &self,
            message: &[u8],
            cert: &CertificateDer<'_>,
            dss: &DigitallySignedStruct,
        ) -> Result<HandshakeSignatureValid, rustls::Error> {
            rustls::crypto::verify_tls13_signature(
                message,
                cert,
                dss,
                &self.provider.signature_verification_algorithms,
            )
        }

        fn supported_verify_schemes(&self) -> Vec<SignatureScheme> {
            self.provider
                .signature_verification_algorithms
                .supported_schemes()
        }
    };
}

/// Accepts exactly one certificate, by fingerprint; signatures are still checked, so the
/// server must hold the certificate's private key.
#[derive(Debug)]
struct PinnedVerifier {
    pinned: Fingerprint,
    provider: Arc<CryptoProvider>,
}

impl ServerCertVerifier for PinnedVerifier {
    fn verify_server_cert(
        &self,
        end_entity: &CertificateDer<'_>,
        _intermediates: &[CertificateDer<'_>],
        _server_name: &ServerName<'_>,
        _ocsp: &[u8],
        _now: UnixTime,
    ) -> Result<ServerCertVerified, rustls::Error> {
        let got = fingerprint_of(end_entity);
        if crate::secret::ct_eq(&got, &self.pinned) {
            Ok(ServerCertVerified::assertion())
        } else {
            // (The pinned value abbreviated: a secret pinned by mistake is not logged.)
            Err(rustls::Error::General(format!(
                "server certificate {} is not the pinned {}",
                to_hex(&got),
                abbreviated(&to_hex(&self.pinned))
            )))
        }
    }

    handshake_signatures!();
}

/// The SHA-256 fingerprint of the certificate the remote side of `conn` presented (a
/// server always does; a client does when the server demanded it).
pub fn peer_fingerprint(conn: &quinn::Connection) -> Option<Fingerprint> {
    let any = conn.peer_identity()?;
    let certs = any.downcast::<Vec<CertificateDer<'static>>>().ok()?;
    certs.first().map(|c| fingerprint_of(c))
}

/// Demands a client certificate and checks the client's handshake signature with it, so
/// the client holds the key; which certificate is acceptable is decided after the
/// handshake, by fingerprint, against the rank the client claims.
#[derive(Debug)]
struct AnyClientCert {
    provider: Arc<CryptoProvider>,
}

impl ClientCertVerifier for AnyClientCert {
    fn root_hint_subjects(&self) -> &[rustls::DistinguishedName] {
        &[]
    }

    fn verify_client_cert(
        &self,
        _end_entity: &CertificateDer<'_>,
        _intermediates: &[CertificateDer<'_>],
        _now: UnixTime,
    ) -> Result<ClientCertVerified, rustls::Error> {
        Ok(ClientCertVerified::assertion())
    }

    fn client_auth_mandatory(&self) -> bool {
        true
    }

    handshake_signatures!();
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fingerprint_hex_round_trip() {
        let id = Identity::generate().unwrap();
        let hex = to_hex(&id.fingerprint);
        assert_eq!(parse_fingerprint(&hex).unwrap(), id.fingerprint);
        let colons: Vec<String> = id.fingerprint.iter().map(|b| format!("{b:02X}")).collect();
        assert_eq!(
            parse_fingerprint(&colons.join(":")).unwrap(),
            id.fingerprint
        );
        assert!(parse_fingerprint("abc").is_err());
        assert_ne!(Identity::generate().unwrap().fingerprint, id.fingerprint);
        // A secret given where a fingerprint belongs is not echoed whole.
        let secret = "0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcdeg";
        let e = parse_fingerprint(secret).unwrap_err().to_string();
        assert!(
            !e.contains("89abcdef0123") && e.contains("\"01234567\"… (64 characters)"),
            "{e}"
        );
    }
}
