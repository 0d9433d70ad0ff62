// Volume I/O through ITK, which converts NIfTI's RAS to LPS and honours direction cosines.
// Formats are chosen by extension, not through ITK's global factory registry, so the
// error for an unknown file type is ours and clear.
#include <itkGDCMImageIO.h>
#include <itkGDCMSeriesFileNames.h>
#include <itkImage.h>
#include <itkImageFileReader.h>
#include <itkImageFileWriter.h>
#include <itkImageSeriesReader.h>
#include <itkMetaImageIO.h>
#include <itkNiftiImageIO.h>
#include <itkNrrdImageIO.h>

#include <zlib.h>

#include <algorithm>
#include <cstring>
#include <filesystem>
#include <cmath>
#include <fstream>
#include <sstream>

#include "cortexfuse/core/error.hpp"
#include "itk_bridge.hpp"
#include "itk_image.hpp"

namespace fs = std::filesystem;

namespace cf::itkb {
namespace {

using FloatImage = itk::Image<float, 3>;

std::string lower(std::string s) {
    std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return char(std::tolower(c)); });
    return s;
}

itk::ImageIOBase::Pointer io_for(const std::string& path) {
    const std::string name = lower(fs::path(path).filename().string());
    auto ends = [&](const std::string& e) {
        return name.size() >= e.size() && name.compare(name.size() - e.size(), e.size(), e) == 0;
    };
    if (ends(".nii") || ends(".nii.gz")) return itk::NiftiImageIO::New().GetPointer();
    if (ends(".nrrd") || ends(".nhdr")) return itk::NrrdImageIO::New().GetPointer();
    if (ends(".mha") || ends(".mhd")) return itk::MetaImageIO::New().GetPointer();
    return nullptr;
}

std::string format_name(const itk::ImageIOBase& io) {
    const std::string c = io.GetNameOfClass();
    if (c == "NiftiImageIO") return "NIfTI";
    if (c == "NrrdImageIO") return "NRRD";
    if (c == "MetaImageIO") return "MetaImage (MHA/MHD)";
    return c;
}

// ITK's description in one line, without its multi-line preamble.
std::string reason(const itk::ExceptionObject& e) {
    std::string d = e.GetDescription();
    for (auto& c : d)
        if (c == '\n' || c == '\r') c = ' ';
    if (d.size() > 300) d = d.substr(0, 300) + "...";
    return d;
}

template <class ImageT>
Grid grid_of(const ImageT* img) {
    Grid g;
    const auto size = img->GetLargestPossibleRegion().GetSize();
    for (int a = 0; a < 3; ++a) {
        g.dims[a] = int(std::min<size_t>(size[a], size_t(1) << 30));
        g.spacing[a] = img->GetSpacing()[a];
        g.origin[a] = img->GetOrigin()[a];
        for (int b = 0; b < 3; ++b) g.direction[a * 3 + b] = img->GetDirection()(a, b);
    }
    return g;
}

// ITK's NIfTI reader accepts a truncated .nii.gz and returns zeros for the missing part,
// so the byte count the header promises is checked here first (the whole gzip stream is
// read and its CRC checked by zlib).
void check_nifti_complete(const std::string& path) {
    gzFile f = gzopen(path.c_str(), "rb");
    if (!f) throw InputError(path, "cannot open file");
    unsigned char hdr[348];
    const int got = gzread(f, hdr, sizeof hdr);
    if (got < int(sizeof hdr)) {
        gzclose(f);
        throw InputError(path, "truncated NIfTI header");
    }
    int32_t sizeof_hdr;
    std::memcpy(&sizeof_hdr, hdr, 4);
    if (sizeof_hdr != 348) {  // NIfTI-2 or byte-swapped: leave the check to ITK
        gzclose(f);
        return;
    }
    int16_t dim[8], bitpix;
    float vox_offset, pixdim[8];
    std::memcpy(dim, hdr + 40, sizeof dim);
    std::memcpy(&bitpix, hdr + 72, 2);
    std::memcpy(pixdim, hdr + 76, sizeof pixdim);
    std::memcpy(&vox_offset, hdr + 108, 4);
    // ITK silently takes |pixdim|: a negative or zero spacing is a broken header, not a flip
    // (flips live in the qform/sform), so it is refused rather than guessed.
    for (int a = 1; a <= 3; ++a)
        if (!std::isfinite(pixdim[a]) || !(pixdim[a] > 0)) {
            gzclose(f);
            throw InputError(path, "absurd voxel spacing " + std::to_string(pixdim[a]) + " mm (pixdim[" + std::to_string(a) +
                                       "] in the NIfTI header)");
        }
    uint64_t voxels = 1;
    for (int d = 1; d <= std::clamp<int>(dim[0], 1, 7); ++d) voxels *= uint64_t(std::max<int16_t>(dim[d], 1));
    const uint64_t expected = uint64_t(std::max(vox_offset, 348.f)) + voxels * uint64_t(std::max<int16_t>(bitpix, 8) / 8);
    uint64_t total = sizeof hdr;
    std::vector<unsigned char> buf(1 << 20);
    int n;
    while ((n = gzread(f, buf.data(), unsigned(buf.size()))) > 0) total += uint64_t(n);
    int err = Z_OK;
    const char* msg = gzerror(f, &err);
    const std::string zmsg = msg ? msg : "";
    gzclose(f);
    if (n < 0 || (err != Z_OK && err != Z_STREAM_END))
        throw InputError(path, "truncated or corrupt compressed data (" + zmsg + ")");
    if (total < expected)
        throw InputError(path, "truncated volume: " + std::to_string(total) + " bytes of " + std::to_string(expected) +
                                   " the header promises");
}

// Key/value lines of a text header: MetaImage ("Key = value") up to ElementDataFile, or a
// NRRD header ("key: value") up to its blank line.
std::vector<std::pair<std::string, std::string>> header_fields(const std::string& path, char sep, const char* last_key) {
    std::ifstream in(path, std::ios::binary);
    std::vector<std::pair<std::string, std::string>> out;
    std::string line;
    size_t read = 0;
    while (read < 65536 && std::getline(in, line)) {
        read += line.size() + 1;
        if (!line.empty() && line.back() == '\r') line.pop_back();
        if (line.empty() && sep == ':') break;
        const auto at = line.find(sep);
        if (at == std::string::npos) continue;
        auto trim = [](std::string t) {
            const auto a = t.find_first_not_of(" \t"), b = t.find_last_not_of(" \t");
            return a == std::string::npos ? std::string() : t.substr(a, b - a + 1);
        };
        out.emplace_back(lower(trim(line.substr(0, at))), trim(line.substr(at + 1)));
        if (out.back().first == last_key) break;
    }
    return out;
}

// What ITK's MetaImage and NRRD readers get wrong or report only on std::cerr: a detached data
// file that is missing, and non-positive spacings (MetaIO takes them as they are).
void check_text_header(const std::string& path, const std::string& format) {
    const bool meta = format.rfind("MetaImage", 0) == 0;
    const bool nrrd_detached = format == "NRRD" && lower(fs::path(path).extension().string()) == ".nhdr";
    if (!meta && !nrrd_detached) return;
    const auto fields = meta ? header_fields(path, '=', "elementdatafile") : header_fields(path, ':', "");
    for (const auto& [key, value] : fields) {
        if (meta && (key == "elementspacing" || key == "elementsize")) {
            std::istringstream in(value);
            for (std::string t; in >> t;) {
                double v = 0;
                try {
                    v = std::stod(t);
                } catch (const std::exception&) {
                    v = std::nan("");
                }
                if (!std::isfinite(v) || !(v > 0))
                    throw InputError(path, "absurd voxel spacing " + t + " mm (" + key + " in the MetaImage header)");
            }
        }
        const bool data_key = meta ? key == "elementdatafile" : (key == "data file" || key == "datafile");
        if (data_key) {
            const std::string v = value;
            if (v == "LOCAL" || v.rfind("LIST", 0) == 0 || v.find('%') != std::string::npos || v.find(' ') != std::string::npos) continue;
            const fs::path data = fs::path(v).is_absolute() ? fs::path(v) : fs::path(path).parent_path() / v;
            std::error_code ec;
            if (!fs::exists(data, ec))
                throw InputError(path, "its voxel data file " + data.string() + " is missing");
        }
    }
}

FloatImage::Pointer read_series(const std::string& dir, void (*check)(const Grid&, const std::string&)) {
    auto names = itk::GDCMSeriesFileNames::New();
    names->SetUseSeriesDetails(true);
    std::vector<std::string> series;
    try {
        names->SetDirectory(dir);
        series = names->GetSeriesUIDs();
    } catch (const itk::ExceptionObject& e) {
        throw InputError(dir, "cannot scan for DICOM: " + reason(e));
    }
    if (series.empty()) throw InputError(dir, "folder holds no DICOM series");
    if (series.size() > 1)
        throw InputError(dir, "folder holds " + std::to_string(series.size()) + " DICOM series; put one series per folder");
    const auto files = names->GetFileNames(series.front());
    if (files.size() < 2) throw InputError(dir, "DICOM series has fewer than 2 slices");
    auto reader = itk::ImageSeriesReader<FloatImage>::New();
    reader->SetImageIO(itk::GDCMImageIO::New());
    reader->SetFileNames(files);
    try {
        reader->UpdateOutputInformation();
        check(grid_of(reader->GetOutput()), dir);
        reader->Update();
    } catch (const itk::ExceptionObject& e) {
        throw InputError(dir, "unreadable DICOM series: " + reason(e));
    }
    return reader->GetOutput();
}

}  // namespace

void read_float(const std::string& path, Grid& grid, std::vector<float>& voxels,
                void (*check)(const Grid&, const std::string&)) {
    std::error_code ec;
    if (!fs::exists(path, ec)) throw InputError(path, "no such file or folder");
    itk::Object::GlobalWarningDisplayOff();  // our errors say it in one line instead
    FloatImage::Pointer img;
    if (fs::is_directory(path, ec)) {
        img = read_series(path, check);
    } else {
        auto io = io_for(path);
        if (!io)
            throw InputError(path, "unknown volume format (expected .nii, .nii.gz, .nrrd, .nhdr, .mha, .mhd or a DICOM folder)");
        const std::string format = format_name(*io);
        if (fs::file_size(path, ec) == 0 && !ec) throw InputError(path, "empty file, not a " + format + " volume");
        {
            // ITK's readers report an unreadable file as "not this format"; say which it is.
            std::ifstream probe(path, std::ios::binary);
            if (!probe) throw InputError(path, "cannot open file (permissions?)");
        }
        if (!io->CanReadFile(path.c_str())) throw InputError(path, "not a readable " + format + " file");
        check_text_header(path, format);
        auto reader = itk::ImageFileReader<FloatImage>::New();
        reader->SetImageIO(io);
        reader->SetFileName(path);
        try {
            reader->UpdateOutputInformation();
            // Refuse absurd headers before ITK allocates for them (and before the byte count
            // below, which would only call them truncated).
            check(grid_of(reader->GetOutput()), path);
            if (format == "NIfTI") check_nifti_complete(path);
            reader->Update();
        } catch (const itk::ExceptionObject& e) {
            throw InputError(path, "unreadable or truncated volume: " + reason(e));
        } catch (const std::bad_alloc&) {
            throw InputError(path, "volume too large for this machine's memory");
        }
        img = reader->GetOutput();
    }
    grid = grid_of(img.GetPointer());
    const float* p = img->GetBufferPointer();
    voxels.assign(p, p + grid.count());
}

namespace {
template <class PixelT>
void write_image(const std::string& path, const Grid& g, const PixelT* data) {
    using ImageT = itk::Image<PixelT, 3>;
    auto io = io_for(path);
    if (!io) throw InputError(path, "unknown volume format to write (use .nii.gz, .nrrd or .mha)");
    auto img = make_image<ImageT>(g);
    std::copy(data, data + g.count(), img->GetBufferPointer());
    auto w = itk::ImageFileWriter<ImageT>::New();
    w->SetImageIO(io);
    w->SetFileName(path);
    w->SetInput(img);
    w->SetUseCompression(true);
    try {
        w->Update();
    } catch (const itk::ExceptionObject& e) {
        throw InputError(path, "cannot write volume: " + reason(e));
    }
}
}  // namespace

void write_float(const std::string& path, const Grid& grid, const float* voxels) { write_image(path, grid, voxels); }
void write_u8(const std::string& path, const Grid& grid, const uint8_t* voxels) { write_image(path, grid, voxels); }

}  // namespace cf::itkb
